"""Camera self-calibration from 2D joint tracks (Wang & Leow, §4).

Two or more fixed, uncalibrated, scaled orthographic cameras watch the same
walker; given the 2D joints in every view, :func:`self_calibrate` recovers the
rotation and the scale of every camera relative to the first and the metric
3D joints, without a nonlinear search:

1. centre and normalise the tracks, rank-3 factorization ``W = M_hat P_hat``
   (Tomasi–Kanade, eq. 4; missing joints are imputed);
2. the five camera constraints (eqs. 7–11) are linear in ``Omega^-1`` and leave
   the family ``Omega^-1(beta) = Omega_0^-1 + beta Omega_1^-1``; the leading
   minors give the range of ``beta`` where it is positive definite;
3. ``Omega(beta) = adj / det``; the rigid-link constraints give ``E(beta)`` and
   ``F(beta) = f4 / f3^2`` (eqs. 12–13); the real roots of ``f6`` (eq. 14)
   inside the range give the global minimum;
4. Cholesky of ``Omega`` gives ``U``; ``M_hat U^-1 = [R_1; s R_2]`` and
   ``U P_hat`` the metric joints;
5. the reflection (depth reversal) left by Cholesky is decided by how knees
   and elbows bend.

With three or more cameras the camera constraints alone over-determine
``Omega^-1`` and are solved jointly in least squares. When the camera scales
change over time (``scales="varying"``, §4.3) each frame pair gets its own
``U`` from the camera constraints and known length ratios, and a bundle
adjustment over the relative rotations, the per-frame scales and the 3D joints
with constant bone lengths finishes the job.

Beyond the paper, for noisy tracks (on by default with ``refine``): the
noise level is read off the rank-3 residual, the tracks are Wiener-smoothed
in time before the closed form and the bundle adjustment is MAP with the
matching temporal prior (``temporal_prior``); and beta is re-chosen with a
cost whose expectation the noise does not bias (``noise_model``). Both
vanish on noise-free tracks, which stay exact.

References
----------
R. Wang and W. K. Leow, "Human posture sequence estimation using two
un-calibrated cameras", §4.1–4.3, eqs. 4–14.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.fft
import scipy.linalg
import scipy.sparse
import scipy.sparse.linalg
from scipy.optimize import least_squares, minimize_scalar
from scipy.spatial.transform import Rotation

from ._factorization import Factorization, factorize, noise_sigma
from ._selfcal_core import (
    DEPTH_FLIP,
    adj3,
    camera_constraint_rows,
    geodesic_deg,
    proper_rotations,
    kinematic_reflection,
    link_rows,
    nearest_scaled_rotation,
    poly_interp,
    sym_from_vec,
    triangulate,
)
from .joints import JOINT_INDEX, N_JOINTS
from .viewpoint import azimuth_difference_deg

__all__ = ["RIGID_LINKS", "SYMMETRIC_RATIOS", "UPRIGHT_PRIORS", "SelfCalibration", "input_warnings", "named_note",
           "self_calibrate"]

Link = tuple[int, int]
Ratio = tuple[Link, Link, float]


def _link(a: str, b: str) -> Link:
    return (JOINT_INDEX[a], JOINT_INDEX[b])


RIGID_LINKS: tuple[Link, ...] = (
    _link("left_shoulder", "right_shoulder"),
    _link("left_shoulder", "left_elbow"),
    _link("left_elbow", "left_wrist"),
    _link("right_shoulder", "right_elbow"),
    _link("right_elbow", "right_wrist"),
    _link("left_hip", "right_hip"),
    _link("left_hip", "left_knee"),
    _link("left_knee", "left_ankle"),
    _link("right_hip", "right_knee"),
    _link("right_knee", "right_ankle"),
)
"""The links of :data:`estimator.joints.BONES` that are one rigid bone.

``BONES`` minus head–shoulder and shoulder–hip, which span the neck and the
spine: on the CMU walks their length varies by 0.5–1.5 % (docs/SELFCAL.md).
"""

SYMMETRIC_RATIOS: tuple[Ratio, ...] = (
    (_link("left_shoulder", "left_elbow"), _link("right_shoulder", "right_elbow"), 1.0),
    (_link("left_elbow", "left_wrist"), _link("right_elbow", "right_wrist"), 1.0),
    (_link("left_hip", "left_knee"), _link("right_hip", "right_knee"), 1.0),
    (_link("left_knee", "left_ankle"), _link("right_knee", "right_ankle"), 1.0),
)
"""Left and right limbs of equal length: the default length ratios for §4.3."""

LengthPrior = tuple[tuple[Link, ...], tuple[Link, ...], float, float]
"""``(links_a, links_b, ratio, tolerance)``: ``sum |a| / sum |b| = ratio``, log std ``tolerance``."""


@dataclass(frozen=True)
class SelfCalibration:
    """Result of a self-calibration; falsy (with a ``reason``) when it failed.

    Attributes
    ----------
    rotations : ndarray of shape (C, 3, 3) or None
        ``R_c R_0^T`` per camera, ``R_c`` the world-to-camera rotation whose
        rows are the image u axis, the image v axis and the viewing direction.
        ``rotations[0]`` is the identity.
    scales : ndarray of shape (C,) or None
        Scale of each camera relative to camera 0 (``s = s_c / s_0``); the
        median over frames when scales vary.
    joints3d : ndarray of shape (T, 13, 3) or None
        Metric joints in camera 0's frame (x = image u, y = image v, z = viewing
        direction), in camera 0's pixels, origin at each frame's centroid of the
        13 joints (missing ones imputed). NaN where a joint was seen by fewer
        than two cameras.
    frame_scales : ndarray of shape (T, C) or None
        Per-frame relative scales (``scales="varying"`` only).
    reflection_confidence : float
        Weighted share of knee/elbow bending votes that agree with the chosen
        depth orientation, in [0.5, 1]; 0.5 means the reflection is a guess.
    rotvec_cov : ndarray of shape (C, 3, 3) or None
        Posterior covariance of each camera's rotation error as a rotation
        vector, **radians squared**: ``omega`` in ``R_true = exp([omega]x) R``
        (``R`` = ``rotations[c]``; ``omega`` in camera c's axes: x image u,
        y image v, z viewing direction), zeros for camera 0 (the reference);
        from the Laplace approximation at the bundle adjustment's optimum
        (:func:`_laplace_covariance`). Free of gimbal lock, unlike
        :attr:`euler_xyz_cov`. None for the closed form alone
        (``refine=False``; the §4.3 path always refines) and for windows too
        long for it (:data:`LAPLACE_MAX_PARAMS`); NaN if the tracks do not
        determine the rotation; zeros on noise-free tracks.
    scale_std : ndarray of shape (C,) or None
        Posterior standard deviation of ``scales`` (fixed scales with
        ``refine`` only; None otherwise, NaN where undetermined).
    method : str
        ``"wang-leow"``, ``"wang-leow-lsq"`` (3+ cameras),
        ``"wang-leow-varying"``, or a baseline's name.
    start : str
        Where the rotations came from (fixed scales): ``"closed form"`` (the
        paper's, refined or not), or, when the bundle adjustment started
        elsewhere, ``"camera pairs"`` (two-camera closed forms chained
        over the best-conditioned pairs), ``"nearest positive-definite Omega"``
        (the least-squares ``Omega^-1`` with its eigenvalues clipped) or
        ``"given"`` (``initial_rotations``); empty for the baselines.
    notes : tuple of str
        What the tracks do not determine well (:func:`input_warnings`);
        empty when nothing was found.
    reason : str
        Why the estimate failed; empty on success.
    diagnostics : dict
        Intermediate quantities (``beta``, ``beta_range``, the polynomial
        coefficients ``f3``, ``f4``, ``f6``, residuals, counts).
    """

    rotations: np.ndarray | None = None
    scales: np.ndarray | None = None
    joints3d: np.ndarray | None = None
    frame_scales: np.ndarray | None = None
    reflection_confidence: float = 0.5
    method: str = "wang-leow"
    reason: str = ""
    diagnostics: dict[str, Any] = field(default_factory=dict, compare=False)
    rotvec_cov: np.ndarray | None = None
    scale_std: np.ndarray | None = None
    start: str = ""
    notes: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.reason:
            return
        if self.rotations is None or self.scales is None or self.joints3d is None:
            raise ValueError("a successful SelfCalibration needs rotations, scales and joints3d")
        r = np.asarray(self.rotations, dtype=float)
        if r.ndim != 3 or r.shape[1:] != (3, 3):
            raise ValueError(f"rotations must have shape (C, 3, 3), got {r.shape}")
        if not proper_rotations(r):
            raise ValueError("rotations must be proper rotations (orthonormal, det = +1)")

    def __bool__(self) -> bool:
        return not self.reason

    @classmethod
    def failed(cls, reason: str, method: str = "wang-leow", **diagnostics: Any) -> SelfCalibration:
        """A falsy result that says why."""
        return cls(method=method, reason=reason, diagnostics=diagnostics)

    @property
    def euler_xyz_deg(self) -> np.ndarray:
        """Per-camera ``Rotation.as_euler("xyz", degrees=True)``, shape (C, 3)."""
        if self.rotations is None:
            raise ValueError(f"no rotations: self-calibration failed ({self.reason})")
        return Rotation.from_matrix(self.rotations).as_euler("xyz", degrees=True)

    @property
    def euler_xyz_cov(self) -> np.ndarray | None:
        """Posterior covariance of each camera's ``euler_xyz_deg`` (C, 3, 3), degrees squared, or None:
        :attr:`rotvec_cov` through the Jacobian of ``as_euler`` (kept for the Euler outputs; it blows
        up near gimbal lock, y = +-90 deg)."""
        if self.rotvec_cov is None:
            return None
        return _euler_covariance(self.rotations, scipy.linalg.block_diag(*self.rotvec_cov[1:]))

    @property
    def euler_xyz_std_deg(self) -> np.ndarray | None:
        """Per-camera posterior standard deviation of ``euler_xyz_deg``, shape (C, 3), or None."""
        if self.euler_xyz_cov is None:
            return None
        return np.sqrt(np.diagonal(self.euler_xyz_cov, axis1=1, axis2=2))


# --------------------------------------------------------------------------- input


def _check_tracks(tracks: Any) -> np.ndarray:
    try:
        y = np.asarray(tracks, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"tracks must be numeric, shape (C, T, {N_JOINTS}, 2): {exc}") from None
    if y.ndim != 4 or y.shape[2:] != (N_JOINTS, 2):
        raise ValueError(f"tracks must have shape (C, T, {N_JOINTS}, 2), got {y.shape}")
    if y.shape[0] < 2:
        raise ValueError(f"need at least two cameras, got {y.shape[0]}")
    if y.shape[1] < 2:
        raise ValueError(f"need at least two frames, got {y.shape[1]}")
    if np.isinf(y).any():
        raise ValueError("tracks contain inf (use NaN for missing joints)")
    seen = np.isfinite(y).all(axis=-1)
    if (seen.sum(axis=(1, 2)) < 4).any():
        raise ValueError("every camera must see at least 4 joints")
    return y


def _check_links(links: Sequence[Link] | None, ratios: Sequence[Ratio]) -> tuple[list, list]:
    links = list(RIGID_LINKS if links is None else links)
    for ln in links:
        if len(ln) != 2 or not all(0 <= int(i) < N_JOINTS for i in ln) or ln[0] == ln[1]:
            raise ValueError(f"a link must be two different joint indices in [0, {N_JOINTS}), got {ln}")
    out = []
    for r in ratios:
        if len(r) != 3 or float(r[2]) <= 0:
            raise ValueError(f"a length ratio must be (link_a, link_b, ratio > 0), got {r}")
        out.append((_named_link(r[0], "length ratio", r), _named_link(r[1], "length ratio", r), float(r[2])))
    return [tuple(map(int, ln)) for ln in links], out


def _named_link(ln, what: str, item) -> tuple[int, int]:
    """A link named inside a ratio or proportion, as two joint indices; ValueError if it is not one."""
    if len(ln) != 2 or not all(0 <= int(i) < N_JOINTS for i in ln):
        raise ValueError(f"bad link {ln} in {what} {item}")
    return int(ln[0]), int(ln[1])


def _check_proportions(priors: Sequence[LengthPrior]) -> list:
    out = []
    for pr in priors or ():
        if len(pr) != 4 or not float(pr[2]) > 0 or not float(pr[3]) > 0 or not pr[0] or not pr[1]:
            raise ValueError(f"a body proportion must be (links_a, links_b, ratio > 0, tolerance > 0), got {pr}")
        out.append((tuple(_named_link(ln, "body proportion", pr) for ln in pr[0]),
                    tuple(_named_link(ln, "body proportion", pr) for ln in pr[1]), float(pr[2]), float(pr[3])))
    return out


# ------------------------------------------------------------------ the beta family


def _trim(p: np.ndarray, rel: float = 1e-12) -> np.ndarray:
    big = np.abs(p).max(initial=0.0)
    keep = np.nonzero(np.abs(p) > rel * big)[0]
    return p[keep[0]:] if keep.size else np.zeros(1)


def _real_roots(p: np.ndarray) -> np.ndarray:
    p = _trim(p)
    if p.size < 2:
        return np.zeros(0)
    r = np.roots(p)
    scale = 1.0 + np.abs(r)
    return np.sort(r[np.abs(r.imag) < 1e-7 * scale].real)


def _omega_family(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``Omega^-1(beta) = A + beta B`` from eqs. 7–11 (two cameras).

    Returns A (particular, minimum norm), B (homogeneous, unit norm) and the
    singular values of the 5 x 6 system.
    """
    a, b = camera_constraint_rows(motion)
    _, sv, vt = np.linalg.svd(a)
    particular = np.linalg.lstsq(a, b, rcond=None)[0]
    return sym_from_vec(particular), sym_from_vec(vt[-1]), sv


def _pd_interval(a: np.ndarray, b: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Range of beta where ``A + beta B`` is positive definite (leading minors > 0).

    Returns (lo, hi, det coefficients f3, highest first); lo = hi = nan if empty.
    """
    nodes = np.array([-1.0, 0.0, 1.0, 2.0])
    m = a + nodes[:, None, None] * b
    minors = np.stack(
        [m[:, 0, 0], m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0], np.linalg.det(m)], axis=1
    )
    coef = poly_interp(minors, nodes)  # (4, 3)
    breaks = np.unique(np.concatenate([_real_roots(coef[:, k]) for k in range(3)]))
    edges = np.concatenate([[-np.inf], breaks, [np.inf]])
    lo_e, hi_e = edges[:-1], edges[1:]
    with np.errstate(invalid="ignore"):
        probe = np.where(
            np.isfinite(lo_e) & np.isfinite(hi_e), 0.5 * (lo_e + hi_e),
            np.where(np.isfinite(lo_e), lo_e + 1.0 + np.abs(lo_e),
                     np.where(np.isfinite(hi_e), hi_e - 1.0 - np.abs(hi_e), 0.0)),
        )
    vals = np.stack([np.polyval(coef[:, k], probe) for k in range(3)], axis=1)
    pd = (vals > 0).all(axis=1)
    if not pd.any():
        return np.nan, np.nan, coef[:, 2]
    # The positive-definite part of a line is convex: one run of segments.
    idx = np.nonzero(pd)[0]
    best = max(np.split(idx, np.nonzero(np.diff(idx) > 1)[0] + 1), key=len)
    return float(lo_e[best[0]]), float(hi_e[best[-1]]), coef[:, 2]


@dataclass(frozen=True)
class _Beta:
    beta: float = np.nan
    lo: float = np.nan
    hi: float = np.nan
    f3: np.ndarray | None = None
    f4: np.ndarray | None = None
    f6: np.ndarray | None = None
    via: str = "sextic"
    reason: str = ""
    beta0: float = np.nan


def _link_noise_poly(a: np.ndarray, b: np.ndarray, motion: np.ndarray, structure: np.ndarray,
                     valid: np.ndarray, links: Sequence[Link], sigma: float) -> np.ndarray:
    """Expected noise part ``v4`` of ``f4`` as a quartic in beta (up to a positive factor).

    Why: noise adds ``v4(beta)`` to the expectation of ``f4(beta)``, and ``v4``
    depends on beta, so the minimum of the paper's ``f4 / f3^2`` moves away
    from the truth as the noise grows (Test 2 geometry, walk 07_05: -15
    degrees of bias at 5 %, docs/SELFCAL.md).
    ``E[f4] = S + v4`` with ``S >= 0`` and ``S = 0`` at the true beta, so
    ``f4 / v4`` has its expected minimum (1) at the truth: the same idea as
    Sampson's error / Kanatani's renormalisation for algebraic fits.

    With i.i.d. image noise of variance ``sigma^2`` the affine joints are
    ``P_hat = M_hat^+ W`` with covariance ``sigma^2 S0``, ``S0 = (M_hat^T M_hat)^-1``,
    and a link vector ``d = P_a - P_b`` of one frame has ``2 sigma^2 S0`` (per-frame
    centring cancels in the difference). For a rigid-link row ``q_t - mean(q)``,
    ``q_t = d_t^T K d_t`` with ``K = adj(Omega^-1(beta))``, the noise adds on average
    ``Var(q_t) = 4 d^T K S K d - 2 tr((K S)^2)`` (unbiased in the observed ``d``,
    ``S = 2 sigma^2 S0``) to the squared residual. Returns the quartic
    ``sum_t Var(q_t) / (2 sigma^2)``, highest coefficient first; finite at
    ``sigma = 0``.
    """
    ln = np.asarray(links, dtype=int).reshape(-1, 2)
    ok = valid[:, ln[:, 0]] & valid[:, ln[:, 1]]
    ok &= (ok.sum(axis=0) >= 2)[None, :]
    d = (structure[:, ln[:, 0]] - structure[:, ln[:, 1]])[ok]  # (N, 3)
    s0 = np.linalg.inv(motion.T @ motion)
    nodes = np.array([-2.0, -1.0, 0.0, 1.0, 2.0])
    k = adj3(a + nodes[:, None, None] * b)  # (5, 3, 3), quadratic in beta
    quad = np.einsum("ni,sij,nj->s", d, k @ s0 @ k, d)
    ks = k @ s0
    tr2 = np.einsum("sij,sji->s", ks, ks)
    return poly_interp(4.0 * quad - 4.0 * sigma**2 * d.shape[0] * tr2, nodes)


def _solve_beta(a: np.ndarray, b: np.ndarray, g: np.ndarray, v4: np.ndarray | None = None) -> _Beta:
    """Global minimum of ``F(beta) = f4 / f3^2`` on the valid range (eqs. 12–14).

    Parameters
    ----------
    a, b : ndarray of shape (3, 3)
        ``Omega^-1(beta) = a + beta b``.
    g : ndarray of shape (M, 6)
        Rigid-link rows, ``g @ vec(Omega) = 0``.
    v4 : ndarray of shape (5,), optional
        The expected noise part of ``f4`` (:func:`_link_noise_poly`). When
        given, the cost is ``f4 / v4`` instead of ``f4 / f3^2``.
    """
    lo, hi, f3 = _pd_interval(a, b)
    if np.isnan(lo):
        return _Beta(reason="no positive-definite Omega^-1 satisfies the camera constraints "
                            "(noise too large or degenerate views)")
    if not (np.isfinite(lo) and np.isfinite(hi)):
        return _Beta(lo=lo, hi=hi, reason="the camera constraints leave an unbounded family "
                                          "(the views are too similar)")
    # adj(A + beta B) is quadratic in beta: coefficients K (3, 6) for [b^2, b, 1].
    nodes = np.array([-1.0, 0.0, 1.0])
    adj = adj3(a + nodes[:, None, None] * b)
    k = poly_interp(adj[:, [0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]], nodes)  # (3, 6)
    c = g @ k.T  # E(beta) = C [b^2, b, 1]^T / f3, eq. 12
    h = c.T @ c
    f4 = np.array([h[0, 0], 2 * h[0, 1], 2 * h[0, 2] + h[1, 1], 2 * h[1, 2], h[2, 2]])
    f6 = np.polysub(np.polymul(np.polyder(f4), f3), 2.0 * np.polymul(f4, np.polyder(f3)))

    def cost(x: np.ndarray | float) -> np.ndarray:
        return np.polyval(f4, x) / np.polyval(f3, x) ** 2

    inside = _stationary(f6, lo, hi)
    if inside.size:
        beta, via = float(inside[np.argmin(cost(inside))]), "sextic"
    else:  # numerically possible only when F is flat; fall back to a bounded search
        width = hi - lo
        res = minimize_scalar(cost, bounds=(lo + 1e-9 * width, hi - 1e-9 * width), method="bounded")
        beta, via = float(res.x), "bounded-search"
    beta0 = beta
    if v4 is not None:
        # d/dbeta (f4 / v4) = f6n / v4^2. Take the minimum of the noise-consistent cost in
        # the basin that holds the paper's minimum (between the neighbouring maxima); a
        # basin that runs out to an end of the range (Omega^-1 singular) keeps the paper's beta.
        f6n = np.polysub(np.polymul(np.polyder(f4), v4), np.polymul(f4, np.polyder(v4)))
        cand = _stationary(f6n, lo, hi)
        curv = np.polyval(np.polyder(_trim(f6n)), cand)
        maxima = cand[curv < 0]
        left = maxima[maxima < beta].max(initial=lo)
        right = maxima[maxima > beta].min(initial=hi)
        minima = cand[(curv > 0) & (cand > left) & (cand < right) & (np.polyval(v4, cand) > 0)]
        if minima.size:
            beta = float(minima[np.argmin(np.abs(minima - beta))])
            via += "+noise-consistent"
        f6 = f6n
    return _Beta(beta, lo, hi, f3, f4, f6, via, beta0=beta0)


def _stationary(f6: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Real roots of ``f6`` strictly inside (lo, hi), polished by two Newton steps."""
    roots = _real_roots(f6)
    df6 = np.polyder(_trim(f6))
    for _ in range(2):  # Newton polish
        d = np.polyval(df6, roots)
        roots = roots - np.where(d != 0, np.polyval(f6, roots) / np.where(d != 0, d, 1.0), 0.0)
    return roots[(roots > lo) & (roots < hi)]


# ------------------------------------------------------------------ reconstruction


def _metric(motion: np.ndarray, structure: np.ndarray, omega_inv: np.ndarray,
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """Cholesky of Omega, cameras ``M_hat U^-1`` and joints ``U P_hat`` in camera 0's frame.

    Parameters
    ----------
    motion : ndarray of shape (2C, 3)
    structure : ndarray of shape (3, N)
    omega_inv : ndarray of shape (3, 3)

    Returns
    -------
    rotations (C, 3, 3), scales (C,) relative to camera 0, joints (N, 3) in
    camera 0's frame and units; or a reason string.
    """
    try:
        lower = np.linalg.cholesky(np.linalg.inv(omega_inv))
    except np.linalg.LinAlgError:
        return "Omega is not positive definite"
    u = lower.T  # Omega = U^T U, U upper triangular
    cams = np.linalg.solve(u.T, motion.T).T  # M_hat U^-1
    pts = u @ structure
    r0, s0 = nearest_scaled_rotation(cams[0:2])
    blocks = (cams @ r0.T).reshape(-1, 2, 3)
    rots, sc = nearest_scaled_rotation(blocks)
    rots[0] = np.eye(3)
    return rots, sc / sc[0], (s0 * (r0 @ pts)).T


def _apply_reflection(rots: np.ndarray, joints: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, bool]:
    flip, conf = kinematic_reflection(joints)
    if flip:
        rots = DEPTH_FLIP @ rots @ DEPTH_FLIP
        joints = joints @ DEPTH_FLIP
    return rots, joints, conf, flip


def _mask_unseen(joints: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """NaN for joints seen by fewer than two cameras; joints (T, J, 3), observed (C, T, J)."""
    return np.where((observed.sum(axis=0) >= 2)[..., None], joints, np.nan)


def _rank_check(fact: Factorization, rank_tol: float) -> str:
    sv = fact.singular_values
    if sv.shape[-1] < 3:
        return "too few joint observations for a rank-3 factorization"
    ratio = sv[:, 2] / np.maximum(sv[:, 0], 1e-300)
    if (ratio < rank_tol).any():
        return (f"degenerate input: the centred tracks have rank < 3 (sigma3/sigma1 = "
                f"{ratio.min():.2e}); the motion is planar or the views coincide")
    return ""


def self_calibrate(
    tracks: np.ndarray,
    *,
    scales: str = "fixed",
    links: Sequence[Link] | None = None,
    length_ratios: Sequence[Ratio] | None = None,
    refine: bool | None = None,
    rank_tol: float = 1e-6,
    max_nfev: int = 200,
    temporal_prior: bool | float | None = None,
    noise_model: bool | None = None,
    body_proportions: Sequence[LengthPrior] = (),
    upright: bool | float = False,
    initial_rotations: np.ndarray | None = None,
) -> SelfCalibration:
    """Self-calibrate scaled orthographic cameras from 2D joint tracks.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, 13, 2)
        Image ``(u, v)`` of the 13 joints (DESIGN.md order) per camera and
        frame, ``C >= 2``, ``T >= 2``; NaN marks a missing joint.
    scales : {"fixed", "varying"}
        ``"fixed"``: one scale per camera, the closed form of §4.2 (eqs. 4–14).
        ``"varying"``: scales change per frame, one ``U`` per frame pair from
        the camera constraints and ``length_ratios``, then a bundle
        adjustment (§4.3).
    links : sequence of (int, int), optional
        Joint pairs of constant length; default :data:`RIGID_LINKS`.
    length_ratios : sequence of ((int, int), (int, int), float), optional
        Known length ratios ``|link_a| / |link_b|`` (first kind of rigid-link
        constraint). Default: none for ``"fixed"``, :data:`SYMMETRIC_RATIOS`
        for ``"varying"``.
    refine : bool, optional
        Finish with the bundle adjustment (§4.3); default False for
        ``"fixed"`` (pure closed form), True for ``"varying"``.
    rank_tol : float
        ``sigma_3 / sigma_1`` of the centred tracks below this is degenerate
        (planar motion or coincident views).
    max_nfev : int
        Function evaluations of the bundle adjustment.
    temporal_prior : bool or float, optional
        Use that the tracks are a smooth motion sampled at a fixed rate (the
        frames must be consecutive and equally spaced) while the noise is
        independent per frame (:func:`_temporal_prior`): the closed form runs
        on Wiener-smoothed tracks, and the bundle adjustment is MAP with a
        prior on the spectrum of every predicted image track instead of
        maximum likelihood. Its strength is set from the data (noise from the
        rank-3 residual, signal spectrum from the tracks); noise-free tracks
        are left unchanged. Default: on when ``refine`` is (and for
        ``"varying"``), off for the bare closed form. ``False`` gives the
        paper's method; a float scales the estimated noise (``True`` = 1).
    noise_model : bool, optional
        Two cameras, ``"fixed"``, no ``length_ratios``: choose beta with the
        noise-consistent cost ``f4 / v4`` (``v4`` = the part of ``f4`` that image noise adds on
        average, :func:`_link_noise_poly`) in the basin of the paper's minimum
        of ``f4 / f3^2``, which noise biases (docs/SELFCAL.md). Default: on
        when ``refine`` is, off for the bare closed form.
    body_proportions : sequence of (links_a, links_b, ratio, tolerance)
        Known proportions of *this* walker, for the bundle adjustment
        (``scales="fixed"`` with ``refine``): ``sum |a| / sum |b|`` over the links (all in ``links``)
        is ``ratio``, with ``tolerance`` the standard deviation of its log.
        MAP residuals weighted by ``noise sigma / tolerance``
        (:func:`_length_prior`), absent on noise-free tracks. Population
        proportions are not accurate enough (docs/SELFCAL.md). Default none.
    upright : bool or float
        Prior that the walker is upright with the arms swinging along the
        walk, for the bundle adjustment (``scales="fixed"`` with ``refine``):
        the mean trunk axis is perpendicular to the mean hip and shoulder
        lines, the mean upper-arm direction to the shoulder line
        (:data:`UPRIGHT_PRIORS`; angles within the body, so no camera or
        ground orientation is needed). MAP residuals weighted by
        ``noise sigma / tolerance``, absent on noise-free tracks. A float
        scales the weight (``True`` = 1). Default off.
    initial_rotations : ndarray of shape (C, 3, 3), optional
        Another start for the bundle adjustment (``refine`` only): rotations
        relative to camera 0 known roughly from elsewhere (e.g. the rig the
        silhouettes' viewpoints give, :func:`estimator.rig.viewpoint_rotations`).
        The joints are triangulated from them with the closed form's scales;
        the result is the start whose adjustment ends at the lower cost
        (``diagnostics["start"]``: ``"closed form"`` or ``"given"``). The
        closed form on noisy tracks can land in the wrong basin (a mirrored or
        tilted rig) that the adjustment alone does not leave.

    Returns
    -------
    SelfCalibration
        Falsy with a ``reason`` when the input is degenerate or no positive
        definite ``Omega`` exists (with ``refine`` and three or more cameras,
        only when no other start exists either: :func:`_fallback_starts`;
        ``start`` says which ran). ``notes``: what the input determines
        poorly (:func:`input_warnings`).

    Raises
    ------
    ValueError
        On malformed input (shape, fewer than two cameras or frames, bad links).

    Notes
    -----
    Two cameras use the one-parameter family of eqs. 7–11 and the sextic of
    eq. 14; three or more cameras solve eqs. 7–11 for every camera jointly in
    least squares (``2C + 1`` equations, 6 unknowns) and need no rigid links.
    """
    y = _check_tracks(tracks)
    if scales not in ("fixed", "varying"):
        raise ValueError(f"scales must be 'fixed' or 'varying', got {scales!r}")
    if length_ratios is None:
        length_ratios = SYMMETRIC_RATIOS if scales == "varying" else ()
    links_, ratios = _check_links(links, length_ratios)
    if refine is None:
        refine = scales == "varying"
    strength = float(refine if temporal_prior is None else temporal_prior)
    noise_model = bool(refine if noise_model is None else noise_model)
    upright_w = float(upright)
    if not (np.isfinite(upright_w) and upright_w >= 0):
        raise ValueError(f"upright must be a bool or a float >= 0, got {upright!r}")
    body_proportions = _check_proportions(body_proportions)
    if not (np.isfinite(strength) and strength >= 0):
        raise ValueError(f"temporal_prior must be a bool or a float >= 0, got {temporal_prior!r}")
    if scales == "varying":
        return _varying(y, links_, ratios, rank_tol=rank_tol, max_nfev=max_nfev,
                        strength=strength)

    n_cam = y.shape[0]
    method = "wang-leow" if n_cam == 2 else "wang-leow-lsq"
    fact = factorize(y)
    reason = _rank_check(fact, rank_tol)
    if reason:
        return SelfCalibration.failed(reason, method)
    t, j = y.shape[1], y.shape[2]
    diag: dict[str, Any] = {"imputation_iterations": fact.iterations,
                            "singular_values": fact.singular_values[0, :4].tolist()}
    prior_op, fcf = None, fact
    if strength > 0:  # closed form on the Wiener-smoothed tracks, MAP bundle adjustment
        prior_op, smoother, prior_diag = _temporal_prior(y / fact.norm, fact, strength)
        diag["temporal_prior"] = dict(prior_diag, strength=strength)
        if smoother is not None:
            fcf = factorize(_smooth_tracks(y, smoother, fact))
            if _rank_check(fcf, rank_tol):
                fcf = fact
    motion, structure = fcf.motion[0], fcf.structure[0]
    if n_cam == 2:
        a, b, _ = _omega_family(motion)
        valid = fact.observed.all(axis=0)
        g = link_rows(structure.T.reshape(t, j, 3), valid, links_, ratios)
        if g.shape[0] < 1:
            return SelfCalibration.failed(
                "no rigid-link constraint: need a link seen whole by every camera in two frames",
                method)
        v4 = None
        if noise_model and links_ and not ratios:  # v4 models the constant-length rows only
            v4 = _link_noise_poly(a, b, motion, structure.T.reshape(t, j, 3), valid, links_,
                                  noise_sigma(fcf))
        sol = _solve_beta(a, b, g, v4)
        if sol.reason:
            return SelfCalibration.failed(sol.reason, method, beta_range=(sol.lo, sol.hi))
        omega_inv = a + sol.beta * b
        diag.update(beta=sol.beta, beta_paper=sol.beta0, beta_range=(sol.lo, sol.hi), beta_via=sol.via,
                    f3=sol.f3, f4=sol.f4, f6=sol.f6, n_link_rows=int(g.shape[0]),
                    omega0_inv=a, omega1_inv=b, v4=v4)
    else:
        a_rows, b_rhs = camera_constraint_rows(motion)
        vec, *_ = np.linalg.lstsq(a_rows, b_rhs, rcond=None)
        omega_inv = sym_from_vec(vec)
        diag.update(camera_residual=float(np.linalg.norm(a_rows @ vec - b_rhs)))
    out = _metric(motion, structure, omega_inv)
    yn, tr_n = y / fact.norm, fact.centroids / fact.norm
    start = "closed form"
    if isinstance(out, str):
        reason = out + " (camera constraints in least squares)"
        if not refine:
            return SelfCalibration.failed(reason, method)
        # The refined path does not need the closed form itself, only a start for the
        # bundle adjustment: every start that can be had, the lowest final cost wins.
        starts = _fallback_starts(yn, fact.observed, motion, omega_inv, links_, strength, rank_tol)
        if not starts:
            return SelfCalibration.failed(reason + "; no camera pair could be chained to every camera either",
                                          method)
        diag.update(closed_form=reason, fallback_starts={name: info for name, *_, info in starts})
        starts = [starts[0][:-1]]  # from either start the adjustment ends at the same cost on the failing rigs
        rots, sc = starts[0][1], starts[0][2]
    else:
        rots, sc, pts = out
        joints = pts.reshape(t, j, 3) * fcf.norm
        rots, joints, conf, flip = _apply_reflection(rots, joints)
        diag["reflected"] = flip
        starts = [(start, rots, sc, joints / fact.norm, tr_n)]
    frame_scales, rot_cov, scale_std = None, None, None
    if refine:
        sigma = noise_sigma(fact)
        if initial_rotations is not None:
            given = _check_rotations(initial_rotations, n_cam)
            starts.append(("given", given, sc, triangulate(yn, fact.observed, given, sc, tr_n), tr_n))
        runs = [(name, _bundle_adjust(yn, fact.observed, r0, np.repeat(s0[:, None], t, axis=1),
                                      x0, c0, links_,
                                      per_frame_scales=False, max_nfev=max_nfev, prior_op=prior_op,
                                      length_prior=_length_prior(body_proportions, links_, sigma),
                                      angle_prior=_angle_prior(UPRIGHT_PRIORS, sigma, upright_w),
                                      noise_sigma=sigma))
                for name, r0, s0, x0, c0 in starts]
        start, ba = min(runs, key=lambda run: run[1][4]["cost_end"])
        if len(runs) > 1 or start != "closed form":
            diag.update(start=start, start_costs={name: run[4]["cost_end"] for name, run in runs})
        rots, sc_t, joints_n, cov, info = ba
        sc = sc_t[:, 0] / sc_t[0, 0]
        if cov is not None:
            rot_cov = _rotvec_blocks(cov, n_cam)
            scale_std = np.concatenate([[0.0], sc[1:] * np.sqrt(np.diag(cov)[3 * (n_cam - 1):])])
        joints = joints_n * fact.norm * sc_t[0, 0]
        _, conf = kinematic_reflection(joints)
        diag.update(bundle=info)
        method += "+ba"
    joints = _mask_unseen(joints, fact.observed)
    return SelfCalibration(rots, sc, joints, frame_scales, conf, method, "", diag, rot_cov, scale_std,
                           start=start, notes=tuple(input_warnings(y, rots, joints)))


PLANAR_RATIO = 0.05
"""Third over first singular value of the metric joints (centred per frame, all frames) below
which the motion is reported as near-planar; a walker's body gives 0.2-0.3."""
SAME_AXIS_DEG = 10.0
"""Two cameras whose relative rotation is below this look along nearly the same axis."""
MIN_FRAMES = 10
"""A camera that sees at least 4 joints in fewer frames than this (or than a quarter of the frames) is reported."""


def input_warnings(tracks: np.ndarray, rotations: np.ndarray, joints3d: np.ndarray) -> list[str]:
    """What 2D joint tracks determine poorly, as sentences for a result's ``notes``.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, 13, 2)
        The tracks calibrated (NaN = missing).
    rotations : ndarray of shape (C, 3, 3)
        The estimated ``R_c R_0^T``.
    joints3d : ndarray of shape (T, 13, 3)
        The estimated joints (any unit; NaN allowed).

    Returns
    -------
    list of str
        Near-planar motion (:data:`PLANAR_RATIO`), cameras looking along nearly the
        same axis (:data:`SAME_AXIS_DEG`), cameras that see the walker in too few
        frames (:data:`MIN_FRAMES`); empty when none applies. Cameras are named by index.
    """
    notes = []
    x = np.asarray(joints3d, float)
    seen = np.isfinite(x).all(axis=-1)
    centre = np.where(seen[..., None], x, 0.0).sum(axis=1) / np.maximum(seen.sum(axis=1), 1)[:, None]
    x = (x - centre[:, None])[seen]
    if len(x) >= 3:
        sv = np.linalg.svd(x, compute_uv=False)
        if sv[2] < PLANAR_RATIO * sv[0]:
            notes.append(f"near-planar motion: the joints span little depth (3rd / 1st singular value "
                         f"{sv[2] / sv[0]:.3f} < {PLANAR_RATIO}); the rotations about the plane are poorly determined")
    n_cam = len(rotations)
    for a in range(n_cam):
        for b in range(a + 1, n_cam):
            angle = float(geodesic_deg(rotations[a], rotations[b]))
            if angle < SAME_AXIS_DEG:
                notes.append(f"cameras {a} and {b} look along nearly the same axis (relative rotation {angle:.1f} deg "
                             f"< {SAME_AXIS_DEG:g}): their relative scale and depth are poorly determined")
    y = np.asarray(tracks, float)
    frames = (np.isfinite(y).all(axis=-1).sum(axis=2) >= 4).sum(axis=1)
    need = max(MIN_FRAMES, int(np.ceil(y.shape[1] / 4)))
    for c in np.nonzero(frames < need)[0]:
        notes.append(f"camera {c} sees the walker (4+ joints) in only {frames[c]} of {y.shape[1]} frames "
                     f"(fewer than {need}): its rotation rests on few poses")
    return notes


def named_note(note: str, cameras: Sequence[str]) -> str:
    """A note of :func:`input_warnings` with the cameras' names in place of their indices."""
    return re.sub(r"\bcameras? (\d+)(?: and (\d+))?", lambda m: ("cameras " if m.group(2) else "camera ")
                  + " and ".join(repr(cameras[int(g)]) for g in m.groups() if g is not None), note)


def _check_rotations(rotations: np.ndarray, n_cam: int) -> np.ndarray:
    """``initial_rotations`` as (C, 3, 3) proper rotations relative to camera 0."""
    r = np.asarray(rotations, dtype=float)
    if r.shape != (n_cam, 3, 3) or not np.all(np.isfinite(r)):
        raise ValueError(f"initial_rotations must be finite, shape ({n_cam}, 3, 3), got {r.shape}")
    if not proper_rotations(r):
        raise ValueError("initial_rotations must be proper rotations")
    return r @ r[0].T


def _orthographic_fit(y: np.ndarray, observed: np.ndarray, rots: np.ndarray, scales: np.ndarray,
                      iters: int = 4) -> tuple[np.ndarray, np.ndarray, float]:
    """Joints and image translations that fit scaled orthographic cameras to the observed joints alone.

    Alternates the linear triangulation (:func:`_selfcal_core.triangulate`) with
    each camera's per-frame translation (the mean residual of its observed joints),
    started at their centroid: unlike :attr:`Factorization.centroids` nothing
    depends on imputed joints. ``y`` (C, T, J, 2) normalised; returns joints
    (T, J, 3) centred per frame, translations (C, T, 2) and the rms residual.
    """
    count = np.maximum(observed.sum(axis=2), 1)[..., None]
    obs = np.where(observed[..., None], y, 0.0)
    tr = obs.sum(axis=2) / count
    for _ in range(iters):
        x = triangulate(y, observed, rots, scales, tr)
        proj = scales[:, None, None, None] * np.einsum("cij,tkj->ctki", rots[:, :2], x)
        resid = np.where(observed[..., None], y - proj, 0.0)
        tr = resid.sum(axis=2) / count
    x = triangulate(y, observed, rots, scales, tr)
    proj = scales[:, None, None, None] * np.einsum("cij,tkj->ctki", rots[:, :2], x) + tr[:, :, None]
    rms = float(np.sqrt(np.mean(np.sum((proj - y)[observed] ** 2, axis=-1))))
    return x, tr, rms


def _fallback_starts(y: np.ndarray, observed: np.ndarray, motion: np.ndarray, omega_inv: np.ndarray, links: list,
                     strength: float, rank_tol: float) -> list[tuple]:
    """Starts for the bundle adjustment when the closed form over all cameras has no
    positive-definite ``Omega`` (3+ cameras, ``refine``).

    Why it happens (docs/SELFCAL.md, "No rig left behind by the closed form"):
    with cameras 2.5-4 m from a walk of 2.2 m, the walker's image grows by up to
    2x in the cameras the walk heads towards, the tracks are far from rank 3
    and the least-squares camera constraints of all cameras sit near the edge
    of positive definiteness; the detector's errors (e.g. joints cut by the
    image border) tip them over, while each pair's closed form still exists.

    * ``"camera pairs"``: the two-camera closed form (eqs. 7–14, with the
      temporal prior and the noise-consistent beta of the refined path) on
      every pair; a spanning tree from camera 0 over the pairs that succeed,
      best conditioned first (the pair's ``sigma_3 / sigma_1``: nearly opposite
      or coincident views are near rank 2), chains the relative rotations and
      scales. Each pair leaves its own depth reversal; the combination that
      best fits all cameras wins, and the knees and elbows decide the global one.
    * ``"nearest positive-definite Omega"``: the least-squares ``Omega^-1`` with
      its eigenvalues clipped to 5 % of the largest.

    Returns ``[(name, rotations (C, 3, 3), scales (C,), joints (T, J, 3),
    translations (C, T, 2), info), ...]`` in normalised units; empty if neither works.
    """
    n_cam = y.shape[0]
    out = []
    pairs = {}
    for a in range(n_cam):
        for b in range(a + 1, n_cam):
            cal = self_calibrate(y[[a, b]], links=links, refine=False, temporal_prior=strength,
                                 noise_model=True, rank_tol=rank_tol)
            if cal:
                sv = np.asarray(cal.diagnostics["singular_values"])
                pairs[a, b] = (float(sv[2] / sv[0]), cal.rotations[1], float(cal.scales[1]))
    # Prim's maximum spanning tree from camera 0: relative rotation R_b R_a^T and scale s_b / s_a.
    rel: dict[int, tuple[int, np.ndarray, float]] = {}
    tree_sv = []
    while len(rel) < n_cam - 1:
        edges = [(ratio, a, b, r, s) for (a, b), (ratio, r, s) in pairs.items() if (a == 0 or a in rel) != (
            b == 0 or b in rel)]
        if not edges:
            break
        ratio, a, b, r, s = max(edges, key=lambda e: e[0])
        if b == 0 or b in rel:  # solved b, new a: invert the pair
            a, b, r, s = b, a, r.T, 1.0 / s
        rel[b] = (a, r, s)
        tree_sv.append(ratio)
    if len(rel) == n_cam - 1:
        order = list(rel)  # parents come before children

        def chain(flips: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            rots, sc = np.tile(np.eye(3), (n_cam, 1, 1)), np.ones(n_cam)
            for k, c in enumerate(order):
                parent, r, s = rel[c]
                r = DEPTH_FLIP @ r @ DEPTH_FLIP if flips[k] else r
                rots[c], sc[c] = r @ rots[parent], s * sc[parent]
            return rots, sc

        # Depth reversal per pair: the combination that fits best (global reversal: the knees).
        combos = [np.array([(m >> k) & 1 for k in range(n_cam - 1)]) for m in range(2 ** min(n_cam - 2, 8))]
        fits = [(_orthographic_fit(y, observed, *chain(f), iters=2)[2], k) for k, f in enumerate(combos)]
        rots, sc = chain(combos[min(fits)[1]])
        x, tr, rms = _orthographic_fit(y, observed, rots, sc)
        rots, x, _, _ = _apply_reflection(rots, x)
        out.append(("camera pairs", rots, sc, x, tr,
                    {"rms": rms, "tree": {f"{rel[c][0]}-{c}": round(v, 4) for c, v in zip(rel, tree_sv)}}))
    w, v = np.linalg.eigh(omega_inv)
    if w[-1] > 0:
        clipped = (v * np.maximum(w, 0.05 * w[-1])) @ v.T
        rots, sc, _ = _metric(motion, np.zeros((3, 0)), clipped)
        x, tr, rms = _orthographic_fit(y, observed, rots, sc)
        rots, x, _, _ = _apply_reflection(rots, x)
        out.append(("nearest positive-definite Omega", rots, sc, x, tr,
                    {"rms": rms, "eigenvalues": (w / w[-1]).tolist()}))
    return out


# ------------------------------------------------------------------ §4.3 varying scales


def _varying(y: np.ndarray, links: list, ratios: list, *, rank_tol: float, max_nfev: int,
             strength: float = 1.0) -> SelfCalibration:
    method = "wang-leow-varying"
    n_cam, t, j, _ = y.shape
    if not ratios and n_cam == 2:
        raise ValueError("scales='varying' with two cameras needs length_ratios "
                         "(constant length over time cannot be used per frame, §4.3)")
    fact = factorize(y, per_frame=True)
    prior_op, fcf, prior_diag = None, fact, {}
    if strength > 0:  # per-frame closed forms on the Wiener-smoothed tracks, MAP bundle adjustment
        prior_op, smoother, prior_diag = _temporal_prior(y / fact.norm, fact, strength)
        prior_diag["strength"] = strength
        if smoother is not None:
            fcf = factorize(_smooth_tracks(y, smoother, fact), per_frame=True)
    motion, structure = fcf.motion, fcf.structure  # (T, 2C, 3), (T, 3, J)
    sv = fcf.singular_values
    good = sv[:, 2] / np.maximum(sv[:, 0], 1e-300) >= rank_tol
    valid = fact.observed.all(axis=0)
    rots_f = np.full((t, n_cam, 3, 3), np.nan)
    sc_f = np.full((t, n_cam), np.nan)
    pts_f = np.full((t, j, 3), np.nan)
    if n_cam == 2:
        a_rows, b_rhs = camera_constraint_rows(motion)
        part = (np.linalg.pinv(a_rows) @ b_rhs[..., None])[..., 0]
        null = np.linalg.svd(a_rows)[2][:, -1]
        fam_a, fam_b = sym_from_vec(part), sym_from_vec(null)
    else:
        a_rows, b_rhs = camera_constraint_rows(motion)
        om = sym_from_vec((np.linalg.pinv(a_rows) @ b_rhs[..., None])[..., 0])
    for f in np.nonzero(good)[0]:  # one small closed form per frame pair (§4.3)
        if n_cam == 2:
            g = link_rows(structure[f].T[None], valid[f][None], links, ratios, constant_length=False)
            if g.shape[0] < 1:
                continue
            sol = _solve_beta(fam_a[f], fam_b[f], g)
            if sol.reason:
                continue
            omega_inv = fam_a[f] + sol.beta * fam_b[f]
        else:
            omega_inv = om[f]
        out = _metric(motion[f], structure[f], omega_inv)
        if isinstance(out, str):
            continue
        rots_f[f], sc_f[f], pts_f[f] = out
    ok = np.isfinite(sc_f).all(axis=1)
    if not good.any():
        return SelfCalibration.failed(
            "degenerate input: every frame's tracks have rank < 3 (planar pose or coincident views)",
            method)
    if ok.sum() < 2:
        return SelfCalibration.failed(
            f"per-frame self-calibration succeeded in {int(ok.sum())} of {t} frames (need 2)", method)
    # Consistent reflection over frames: each frame is (R, X) or (D R D, X D).
    cand = np.stack([rots_f[ok], DEPTH_FLIP @ rots_f[ok] @ DEPTH_FLIP])  # (2, n, C, 3, 3)
    ref = cand[0, 0]
    for _ in range(3):
        dist = geodesic_deg(ref[None, None, 1:], cand[:, :, 1:]).sum(axis=-1)  # (2, n)
        pick = np.argmin(dist, axis=0)
        chosen = cand[pick, np.arange(pick.size)]
        ref = np.stack([Rotation.from_matrix(chosen[:, c]).mean().as_matrix() for c in range(n_cam)])
    pts_ok = np.where(pick[:, None, None] == 1, pts_f[ok] @ DEPTH_FLIP, pts_f[ok])
    pts_all = np.zeros((t, j, 3))
    pts_all[ok] = pts_ok
    rots, joints, conf, flip = _apply_reflection(ref, pts_all)
    # Bundle adjustment: per-frame size factor as the initial camera-0 scale.
    ln = np.asarray(links, dtype=int).reshape(-1, 2)
    if ln.shape[0]:
        lens = np.linalg.norm(joints[:, ln[:, 0]] - joints[:, ln[:, 1]], axis=-1)  # (T, K)
        ref_len = np.nanmedian(np.where(ok[:, None], lens, np.nan), axis=0)
        kappa = np.nanmedian(lens / ref_len, axis=1)
    else:
        kappa = np.ones(t)
    kappa = np.where(ok & np.isfinite(kappa) & (kappa > 0), kappa, np.nanmedian(kappa[ok]))
    sc_init = np.where(ok[:, None], sc_f, np.nanmedian(sc_f[ok], axis=0)).T * kappa[None, :]
    x_init = joints / kappa[:, None, None] * (fcf.norm / fact.norm)  # _metric: normalised units
    x_init[~ok] = np.nanmedian(x_init[ok], axis=0)
    rots, sc_t, x, cov, info = _bundle_adjust(y / fact.norm, fact.observed, rots, sc_init, x_init,
                                              fact.centroids / fact.norm, links, per_frame_scales=True,
                                              max_nfev=max_nfev, prior_op=prior_op,
                                              noise_sigma=noise_sigma(fact))
    joints = x * fact.norm * sc_t[0, 0]
    _, conf = kinematic_reflection(joints)
    frame_scales = (sc_t / sc_t[0:1]).T
    diag = {"frames_solved": int(ok.sum()), "bundle": info, "reflected": flip,
            "temporal_prior": prior_diag}
    joints = _mask_unseen(joints, fact.observed)
    return SelfCalibration(rots, np.median(frame_scales, axis=0), joints, frame_scales, conf, method, "", diag,
                           None if cov is None else _rotvec_blocks(cov, len(rots)), start="per-frame closed forms",
                           notes=tuple(input_warnings(y, rots, joints)))


def _temporal_prior(y: np.ndarray, fact: Factorization, strength: float = 1.0
                    ) -> tuple[np.ndarray | None, np.ndarray | None, dict]:
    """Temporal prior of the tracks, set from the data: MAP weights and a Wiener smoother.

    The tracks are a smooth motion sampled at a fixed rate, the noise is
    independent per frame. In the orthonormal DCT-II basis over time, the
    per-frame centred image tracks have a power spectrum ``P_k`` (mean of the
    squared coefficient ``k`` over cameras, joints and u, v) that is signal
    ``S_k`` plus the flat noise floor ``sigma_c^2 = sigma^2 (1 - 1/J)``;
    ``sigma`` comes from the rank-3 residual (:func:`noise_sigma`, 0 on
    noise-free tracks) and ``S_k = P_k - sigma_c^2``, floored at the standard
    error of ``P_k``. A zero-mean Gaussian prior with these variances on the
    DCT coefficients of every predicted image track (a stationary prior whose
    spectrum is measured, not assumed) gives

    * the MAP residuals ``(sigma / sqrt(S_k)) DCT_k(track)``, ``k >= 1``, of
      :func:`_bundle_adjust` (the mean pose, ``k = 0``, is free), and
    * the Wiener smoother ``H_k = S_k / (S_k + sigma_c^2)`` (the posterior mean
      of the tracks), applied before the factorization: a linear filter over
      time, so fixed cameras' tracks stay exactly rank 3.

    Both are absent when ``sigma <= 1e-9`` (normalised units: rounding
    error), so noise-free input stays exact. ``strength`` scales the
    estimated noise (1 = as estimated).

    Parameters
    ----------
    y : ndarray of shape (C, T, J, 2)
        Tracks in the units of ``fact`` (pixels / ``fact.norm``), NaN = missing.
    fact : Factorization

    Returns
    -------
    prior_op (T - 1, T) or None, smoother (T, T) or None (both in time, acting
    on frames), diagnostics dict (``noise_sigma`` in those units, ``gain`` =
    ``H_k``).
    """
    c, t, j, _ = y.shape
    sigma = noise_sigma(fact) * strength
    if not sigma > 1e-9 or t < 3:  # below 1e-9 of the tracks' RMS: rounding, not noise
        return None, None, {"noise_sigma": sigma}
    centred = _filled_centred(y, fact)
    dct_m = scipy.fft.dct(np.eye(t), type=2, norm="ortho", axis=0)  # (k, t)
    power = np.mean(np.einsum("kt,ctjd->ckjd", dct_m, centred) ** 2, axis=(0, 2, 3))  # (T,)
    noise = sigma**2 * (1.0 - 1.0 / j)
    signal = np.maximum(power - noise, power * np.sqrt(2.0 / (c * j * 2)))
    gain = signal / (signal + noise)
    gain[0] = 1.0
    prior_op = (sigma / np.sqrt(signal[1:]))[:, None] * dct_m[1:]
    smoother = dct_m.T @ (gain[:, None] * dct_m)
    return prior_op, smoother, {"noise_sigma": sigma, "gain": gain.tolist()}


def _filled_centred(y: np.ndarray, fact: Factorization) -> np.ndarray:
    """Per-frame centred tracks (units of ``y``, normalised), missing entries from the rank-3 fit."""
    c, t, j, _ = y.shape
    fit = np.einsum("gri,gin->grn", fact.motion, fact.structure)
    fit = fit.reshape(2 * c, t, j) if fit.shape[0] == 1 else fit.transpose(1, 0, 2)
    fit = np.moveaxis(fit.reshape(c, 2, t, j), 1, 3)
    centred = y - (fact.centroids / fact.norm)[:, :, None, :]
    return np.where(np.isfinite(centred), centred, fit)


def _smooth_tracks(y: np.ndarray, smoother: np.ndarray, fact: Factorization) -> np.ndarray:
    """Apply the temporal smoother to the per-frame centred tracks (pixels); NaN stays NaN."""
    centred = _filled_centred(y / fact.norm, fact)
    out = np.einsum("ts,csjd->ctjd", smoother, centred) * fact.norm + fact.centroids[:, :, None, :]
    return np.where(np.isfinite(y), out, np.nan)


def _length_prior(priors: Sequence[LengthPrior], links: Sequence[Link],
                  sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
    """Soft length ratios as MAP residuals for :func:`_bundle_adjust`.

    Each prior ``(links_a, links_b, ratio, tol)`` says ``log(sum |a| / sum |b|)``
    is ``log(ratio)`` with standard deviation ``tol``; against image noise of
    standard deviation ``sigma`` (normalised units, the reprojection residuals'
    scale) its residual weight is ``sigma / tol``. Priors that name a
    link outside ``links`` are skipped. None without noise (``sigma <= 1e-9``):
    noise-free tracks stay exact.
    """
    if not sigma > 1e-9 or not priors:
        return None
    index = {tuple(sorted(ln)): i for i, ln in enumerate(links)}
    a_rows, b_rows, log_r, w = [], [], [], []
    for la, lb, ratio, tol in priors:
        keys = [tuple(sorted(map(int, ln))) for ln in (*la, *lb)]
        if not all(key in index for key in keys):
            continue
        a = np.zeros(len(links)); b = np.zeros(len(links))
        for key in keys[:len(la)]:
            a[index[key]] += 1.0
        for key in keys[len(la):]:
            b[index[key]] += 1.0
        a_rows.append(a); b_rows.append(b); log_r.append(np.log(ratio))
        w.append(sigma / tol)
    if not w:
        return None
    return np.array(a_rows), np.array(b_rows), np.array(log_r), np.array(w)


_TRUNK = {"left_shoulder": 0.5, "right_shoulder": 0.5, "left_hip": -0.5, "right_hip": -0.5}
_UPPER_ARMS = {"left_shoulder": 0.5, "right_shoulder": 0.5, "left_elbow": -0.5, "right_elbow": -0.5}
_HIP_LINE = {"left_hip": 1.0, "right_hip": -1.0}
_SHOULDER_LINE = {"left_shoulder": 1.0, "right_shoulder": -1.0}

UPRIGHT_PRIORS: tuple[tuple[dict[str, float], dict[str, float], float], ...] = (
    (_TRUNK, _HIP_LINE, 0.67),
    (_TRUNK, _SHOULDER_LINE, 0.67),
    (_UPPER_ARMS, _SHOULDER_LINE, 1.0),
)
"""Upright walker, arms swinging along the walk: ``(vector a, vector b, tolerance in degrees)``,
each vector a combination of joints averaged over the frames, ``a`` perpendicular to ``b``.

The mean trunk axis (hip centre to shoulder centre) is perpendicular to the
mean hip line and to the mean shoulder line, and so is the mean upper-arm
direction (elbow centre to shoulder centre) to the shoulder line. Angles
inside the body: no camera, ground or heading is needed. On the CMU walks
(30-frame windows, mean +- std) they are 91.1 +- 1.2 / 88.0 +- 0.4 /
88.6 +- 0.7 deg (07_05) and 90.3 +- 0.6 / 88.2 +- 0.5 / 90.9 +- 0.4 deg
(16_15). The set and the tolerances were chosen on 07_05 (docs/SELFCAL.md).
Not for a walker who carries something or holds the arms away from the body.
"""


def _cosines(x: np.ndarray, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cosine between the frame means ``va = mean_t sum_j a_ij x_tj`` and ``vb``, and its gradients."""
    return cosine_gradients(np.einsum("nj,tjd->nd", a, x) / x.shape[0], np.einsum("nj,tjd->nd", b, x) / x.shape[0])


def cosine_gradients(va: np.ndarray, vb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cosine between vectors ``va`` and ``vb`` (..., 3), and its gradients with respect to each."""
    na = np.maximum(np.linalg.norm(va, axis=-1), 1e-12)[..., None]
    nb = np.maximum(np.linalg.norm(vb, axis=-1), 1e-12)[..., None]
    c = np.sum(va * vb, axis=-1, keepdims=True) / (na * nb)
    return c[..., 0], vb / (na * nb) - c * va / na**2, va / (na * nb) - c * vb / nb**2


def _angle_prior(priors, sigma: float, strength: float = 1.0):
    """Perpendicularity priors as MAP residuals ``strength * sigma / tol_rad * cos`` (None without noise)."""
    if not sigma > 1e-9 or not priors or not strength > 0:
        return None
    a = np.zeros((len(priors), N_JOINTS)); b = np.zeros((len(priors), N_JOINTS)); w = []
    for i, (ca, cb, tol) in enumerate(priors):
        for name, v in ca.items():
            a[i, JOINT_INDEX[name]] += v
        for name, v in cb.items():
            b[i, JOINT_INDEX[name]] += v
        w.append(strength * sigma / np.radians(tol))
    return a, b, np.array(w)


def _bundle_adjust(
    y: np.ndarray,
    observed: np.ndarray,
    rots: np.ndarray,
    scales: np.ndarray,
    joints: np.ndarray,
    centroids: np.ndarray,
    links: Sequence[Link],
    *,
    per_frame_scales: bool,
    max_nfev: int,
    bone_weight: float = 1.0,
    prior_op: np.ndarray | None = None,
    length_prior: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None,
    angle_prior: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    noise_sigma: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
    """Bundle adjustment over rotations, scales and 3D joints with constant bone lengths.

    Parameters
    ----------
    y : ndarray of shape (C, T, J, 2)
        Normalised tracks (NaN where missing).
    observed : ndarray of shape (C, T, J), bool
    rots : ndarray of shape (C, 3, 3)
        Initial rotations relative to camera 0 (``rots[0] = I`` stays fixed).
    scales : ndarray of shape (C, T)
        Initial scales; ``scales[0, 0]`` stays fixed (the gauge).
    joints : ndarray of shape (T, J, 3)
        Initial joints in camera 0's frame (normalised units / scale).
    centroids : ndarray of shape (C, T, 2)
        Initial image translations.
    links : sequence of (int, int)
        Links whose length is a free parameter shared over frames.
    per_frame_scales : bool
        One scale per camera and frame (§4.3) or one per camera.
    prior_op : ndarray of shape (K, T), optional
        Temporal prior: residuals ``prior_op @ (predicted image track)`` for
        every camera, joint and image axis (None = maximum likelihood, the
        paper's bundle adjustment); see :func:`_temporal_prior`.
    length_prior : (A, B, log_r, w), optional
        Soft length ratios over the link lengths ``L`` (:func:`_length_prior`):
        residuals ``w (log(A L) - log(B L) - log_r)``, ``A``, ``B`` of shape
        ``(n, len(links))``.
    angle_prior : (A, B, w), optional
        Perpendicularity of frame-mean joint combinations (:func:`_angle_prior`):
        residuals ``w cos(mean_t A x_t, mean_t B x_t)``, ``A``, ``B`` of shape ``(n, J)``.
    noise_sigma : float
        Image noise standard deviation (normalised units) for the posterior
        covariance; 0 gives zeros.

    Returns
    -------
    rotations (C, 3, 3), scales (C, T), joints (T, J, 3), the posterior
    covariance (:func:`_laplace_covariance`; None when too large) of the
    rotation errors ``omega`` of cameras 1.. (``R_hat = exp(omega) R``, in
    radians) and then the free log scales, info dict.

    Notes
    -----
    Residuals: reprojection ``s_ct (R_c X_tj)_{uv} + t_ct - y_ctj`` for every
    observed joint; ``|X_ta - X_tb| - L_k`` per link and frame; each
    frame's joint centroid (the gauge of the per-frame translations); and with
    ``prior_op`` the MAP term ``prior_op @ (s_ct (R_c X_tj)_{uv})_t`` for every
    camera, joint and image axis (the predicted track, centred per frame).
    """
    n_cam, t, j, _ = y.shape
    ln = np.asarray(links, dtype=int).reshape(-1, 2)
    k = ln.shape[0]
    n_rot = 3 * (n_cam - 1)
    n_s = n_cam * t - 1 if per_frame_scales else n_cam - 1
    n_t = 2 * n_cam * t
    n_x = 3 * t * j
    sizes = [n_rot, n_s, n_t, n_x, k]
    offs = np.concatenate([[0], np.cumsum(sizes)])
    log_s0 = np.log(scales[0, 0])
    bone_ok = np.ones((t, k), dtype=bool)
    if k:
        lens = np.linalg.norm(joints[:, ln[:, 0]] - joints[:, ln[:, 1]], axis=-1)
        l0 = np.median(lens, axis=0)
    else:
        l0 = np.zeros(0)
    s_init = np.log(scales.reshape(-1)[1:] if per_frame_scales else scales[1:, 0])
    p0 = np.concatenate([
        Rotation.from_matrix(rots[1:]).as_rotvec().ravel(), s_init,
        centroids.ravel(), joints.ravel(), l0])
    obs_c, obs_t, obs_j = np.nonzero(observed)
    y_obs = y[obs_c, obs_t, obs_j]
    smooth = prior_op is not None and prior_op.size > 0 and t >= 2
    n_ap = 0
    if angle_prior is not None:
        ap_a, ap_b, ap_w = (np.asarray(v, dtype=float) for v in angle_prior)
        n_ap = ap_w.size
    n_lp = 0
    if length_prior is not None and k:
        lp_a, lp_b, lp_r, lp_w = (np.asarray(v, dtype=float) for v in length_prior)
        n_lp = lp_r.size
    if smooth:
        prior_op = np.asarray(prior_op, dtype=float)
        n_k = prior_op.shape[0]
        n_sm = n_cam * n_k * j * 2

    def unpack(p: np.ndarray):
        rv, ls, tr, x, lk = (p[offs[i]:offs[i + 1]] for i in range(5))
        r = np.concatenate([np.eye(3)[None], Rotation.from_rotvec(rv.reshape(-1, 3)).as_matrix()])
        ls_full = np.concatenate([[log_s0], ls])
        s = np.exp(ls_full).reshape(n_cam, t) if per_frame_scales else np.repeat(
            np.exp(ls_full)[:, None], t, axis=1)
        return r, s, tr.reshape(n_cam, t, 2), x.reshape(t, j, 3), lk

    def fun(p: np.ndarray) -> np.ndarray:
        r, s, tr, x, lk = unpack(p)
        proj = np.einsum("cij,tkj->ctki", r[:, :2], x)
        pred = s[obs_c, obs_t, None] * proj[obs_c, obs_t, obs_j] + tr[obs_c, obs_t]
        res = [(pred - y_obs).ravel()]
        if k:
            bl = np.linalg.norm(x[:, ln[:, 0]] - x[:, ln[:, 1]], axis=-1) - lk
            res.append(bone_weight * bl[bone_ok])
        res.append(x.mean(axis=1).ravel())
        if smooth:  # prior on each camera's predicted (centred) image track: (C, K, J, 2)
            track = s[:, :, None, None] * proj
            res.append(np.einsum("kt,ctjd->ckjd", prior_op, track).ravel())
        if n_lp:
            lk_pos = np.maximum(lk, 1e-12)
            res.append(lp_w * (np.log(lp_a @ lk_pos) - np.log(lp_b @ lk_pos) - lp_r))
        if n_ap:
            res.append(ap_w * _cosines(x, ap_a, ap_b)[0])
        return np.concatenate(res)

    # Analytic sparse Jacobian (finite differences only for the rotation vectors).
    n_obs = obs_c.size
    ridx = np.arange(2 * n_obs).reshape(n_obs, 2)
    cam_b = obs_c > 0
    sidx = obs_c * t + obs_t - 1 if per_frame_scales else obs_c - 1
    has = sidx >= 0
    rows, cols = [], []
    for d in range(2):
        rr = ridx[:, d]
        for q in range(3):
            rows.append(rr[cam_b]); cols.append(offs[0] + 3 * (obs_c[cam_b] - 1) + q)
        rows.append(rr[has]); cols.append(offs[1] + sidx[has])
        rows.append(rr); cols.append(offs[2] + (obs_c * t + obs_t) * 2 + d)
        for q in range(3):
            rows.append(rr); cols.append(offs[3] + (obs_t * j + obs_j) * 3 + q)
    base = 2 * n_obs
    bt, bk = np.nonzero(bone_ok) if k else (np.zeros(0, int), np.zeros(0, int))
    if k:
        rb = base + np.arange(bt.size)
        for end in range(2):
            for q in range(3):
                rows.append(rb); cols.append(offs[3] + (bt * j + ln[bk, end]) * 3 + q)
        rows.append(rb); cols.append(offs[4] + bk)
        base += bt.size
    ct, cd, cj = np.meshgrid(np.arange(t), np.arange(3), np.arange(j), indexing="ij")
    rows.append((base + ct * 3 + cd).ravel()); cols.append(offs[3] + ((ct * j + cj) * 3 + cd).ravel())
    base += 3 * t
    if smooth:  # rows (C, K, J, 2); columns: T frames x 3 coordinates, scales, rotation
        pc, pk, pj, pd = (v.ravel() for v in np.meshgrid(
            np.arange(n_cam), np.arange(n_k), np.arange(j), np.arange(2), indexing="ij"))
        rs = base + np.arange(pc.size)
        frames = np.arange(t)
        rows.append(np.repeat(rs, 3 * t))
        cols.append((offs[3] + ((frames[None, :, None] * j + pj[:, None, None]) * 3
                                + np.arange(3)[None, None, :])).ravel())
        if per_frame_scales:
            s_col = (pc[:, None] * t + frames[None, :] - 1).ravel()
            s_row = np.repeat(rs, t)
        else:
            s_col, s_row = pc - 1, rs
        s_has = s_col >= 0
        rows.append(s_row[s_has]); cols.append(offs[1] + s_col[s_has])
        sm_b = pc > 0
        for q in range(3):
            rows.append(rs[sm_b]); cols.append(offs[0] + 3 * (pc[sm_b] - 1) + q)
        base += pc.size
    if n_lp:  # dense (n_lp, k) block on the link lengths
        rl, cl = np.meshgrid(np.arange(n_lp), np.arange(k), indexing="ij")
        rows.append(base + rl.ravel()); cols.append(offs[4] + cl.ravel())
        base += n_lp
    if n_ap:  # dense over all joints and frames (the vectors are means over frames)
        ra_ = np.repeat(base + np.arange(n_ap), n_x)
        rows.append(ra_); cols.append(np.tile(offs[3] + np.arange(n_x), n_ap))
        base += n_ap
    rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)
    shape = (base, offs[-1])
    centroid_vals = np.full(ct.size, 1.0 / j)

    def jac(p: np.ndarray) -> scipy.sparse.csr_matrix:
        r, s, _, x, lk = unpack(p)
        rx = np.einsum("cij,tkj->ctki", r, x)[obs_c, obs_t, obs_j]  # (n_obs, 3)
        sc = s[obs_c, obs_t]
        # Rotation columns: central differences, all cameras' q-th component at once.
        drot, drot_sm = [], []
        h = 1e-6
        for q in range(3):
            dp = np.zeros_like(p)
            dp[offs[0] + q:offs[1]:3] = h
            diff = (fun(p + dp) - fun(p - dp)) / (2 * h)
            drot.append(diff[:2 * n_obs].reshape(n_obs, 2))
            if smooth:
                end = diff.size - n_lp - n_ap
                drot_sm.append(diff[end - n_sm:end])
        vals = []
        for d in range(2):
            for q in range(3):
                vals.append(drot[q][cam_b, d])
            vals.append((sc * rx[:, d])[has])
            vals.append(np.ones(n_obs))
            rd = r[obs_c, d]  # (n_obs, 3)
            for q in range(3):
                vals.append(sc * rd[:, q])
        if k:
            diff = x[bt, ln[bk, 0]] - x[bt, ln[bk, 1]]
            unit = diff / np.maximum(np.linalg.norm(diff, axis=-1, keepdims=True), 1e-12)
            for sign in (1.0, -1.0):
                for q in range(3):
                    vals.append(sign * bone_weight * unit[:, q])
            vals.append(np.full(bt.size, -bone_weight))
        vals.append(centroid_vals)
        if smooth:
            coef = prior_op[pk][:, :, None] * s[pc][:, :, None] * r[pc, pd][:, None, :]  # (n, T, 3)
            vals.append(coef.ravel())
            ds = prior_op[pk] * s[pc] * np.einsum("nq,tnq->nt", r[pc, pd], x[:, pj])  # (n, T)
            vals.append((ds.ravel() if per_frame_scales else ds.sum(axis=1))[s_has])
            for q in range(3):
                vals.append(drot_sm[q][sm_b])
        if n_lp:
            lk_pos = np.maximum(lk, 1e-12)
            vals.append((lp_w[:, None] * (lp_a / (lp_a @ lk_pos)[:, None]
                                          - lp_b / (lp_b @ lk_pos)[:, None])).ravel())
        if n_ap:
            _, ga, gb = _cosines(x, ap_a, ap_b)  # (n, 3) gradients w.r.t. the mean vectors
            dx = (ap_a[:, :, None] * ga[:, None, :] + ap_b[:, :, None] * gb[:, None, :]) / t  # (n, J, 3)
            vals.append((ap_w[:, None, None, None] * np.broadcast_to(dx[:, None], (n_ap, t, j, 3))).ravel())
        return scipy.sparse.csr_matrix((np.concatenate(vals), (rows_a, cols_a)), shape=shape)

    start_cost = 0.5 * float(np.sum(fun(p0) ** 2))
    res = least_squares(fun, p0, jac=jac, method="trf", x_scale="jac", max_nfev=max_nfev)
    r, s, _, x, _ = unpack(res.x)
    cov = _laplace_covariance(jac(res.x), noise_sigma, n_rot + n_s, dense=smooth or n_ap > 0)
    if cov is not None and n_rot:  # rotation vectors -> rotation errors, whatever their length
        g = np.eye(n_rot + n_s)
        g[:n_rot, :n_rot] = _local_rotation_jacobian(res.x[:n_rot].reshape(-1, 3))
        bad = (np.abs(g) > 0) @ np.isnan(np.diag(cov)) > 0  # undetermined stays undetermined
        cov = g @ np.nan_to_num(cov) @ g.T
        cov[bad] = np.nan
        cov[:, bad] = np.nan
    info = {"cost_start": start_cost, "cost_end": float(res.cost), "nfev": int(res.nfev),
            "status": int(res.status)}
    return r, s, x, cov, info


LAPLACE_MAX_PARAMS = 6000
"""Above this many bundle-adjustment parameters (about 150 frames x 13 joints
with two cameras) the dense posterior covariance is not computed (memory grows
with its square): windows are meant to be short."""


def _laplace_covariance(jac: scipy.sparse.spmatrix, sigma: float, n: int, *,
                        dense: bool = True) -> np.ndarray | None:
    """Posterior covariance of the first ``n`` bundle-adjustment parameters (Laplace approximation).

    The cost is ``sigma^2`` times the negative log-posterior (reprojection
    residuals of standard deviation ``sigma``; the MAP residuals weighted to
    match; the bone-length residuals, weight 1, a soft prior of standard
    deviation ``sigma`` on each length), so near the optimum the posterior is
    Gaussian with covariance ``sigma^2 (J^T J)^-1`` (the Gauss–Newton Hessian;
    on Test 2 the errors match it: docs/SELFCAL.md). ``dense``: Cholesky of
    ``J^T J``, for when the temporal or the angle prior couples all frames
    (a sparse factorisation fills in and is slower; about 50 ms for 30 frames
    x 13 joints); otherwise a sparse LU, whose fill stays within frames.
    Parameters that the tracks do not determine (``J^T J`` singular: e.g. a
    joint no camera sees, without the temporal prior) get the inverse on the
    range, exact for the others; rows and columns of the first ``n`` that the
    free directions touch are NaN. Zeros when ``sigma <= 1e-9`` (noise-free);
    None above :data:`LAPLACE_MAX_PARAMS` with ``dense``.
    """
    if not sigma > 1e-9:
        return np.zeros((n, n))
    jac = scipy.sparse.csr_matrix(jac)
    if dense and jac.shape[1] > LAPLACE_MAX_PARAMS:
        return None
    h = jac.T @ jac
    try:
        if dense:
            cov = scipy.linalg.cho_solve(scipy.linalg.cho_factor(h.toarray()), np.eye(h.shape[0], n))
        else:
            cov = scipy.sparse.linalg.splu(scipy.sparse.csc_matrix(h)).solve(np.eye(h.shape[0], n))
        cov, touched = cov[:n], np.zeros(n, dtype=bool)
    except (np.linalg.LinAlgError, RuntimeError):  # singular: the inverse on the range (slower)
        w, v = np.linalg.eigh(h.toarray())
        free = w <= 1e-10 * w[-1]
        touched = np.abs(v[:n, free]).max(axis=1, initial=0.0) > 1e-6
        cov = (v[:n, ~free] / w[~free]) @ v[:n, ~free].T
    cov = sigma**2 * 0.5 * (cov + cov.T)
    cov[touched] = np.nan
    cov[:, touched] = np.nan
    return cov


def _central_jacobian(f, n: int, h: float = 1e-6, degrees: bool = False) -> np.ndarray:
    """``d f / d x`` at ``x = 0`` by central differences; ``f`` maps ``(2n, n)`` steps to ``(2n, m)``
    values. ``degrees``: the values are angles, wrapped between the two steps."""
    v = f(h * np.concatenate([np.eye(n), -np.eye(n)]))
    d = azimuth_difference_deg(v[:n], v[n:]) if degrees else v[:n] - v[n:]
    return d.T / (2 * h)


def _local_rotation_jacobian(rotvecs: np.ndarray) -> np.ndarray:
    """Block diagonal ``d omega / d rv``: how the bundle adjustment's rotation vectors
    move each rotation, as ``omega = log(R(rv + d) R(rv)^T)`` (a rotation in camera c's frame)."""
    out = np.zeros((3 * len(rotvecs), 3 * len(rotvecs)))
    for c, rv in enumerate(rotvecs):
        r0 = Rotation.from_rotvec(rv).inv()
        out[3 * c:3 * c + 3, 3 * c:3 * c + 3] = _central_jacobian(
            lambda d, rv=rv, r0=r0: (Rotation.from_rotvec(rv[None] + d) * r0).as_rotvec(), 3)
    return out


def _rotvec_blocks(cov: np.ndarray, n_cam: int) -> np.ndarray:
    """Each camera's (3, 3) block of the rotation errors' covariance (the first ``3 (C - 1)`` rows and
    columns of the bundle adjustment's, radians^2), zeros for camera 0: shape (C, 3, 3)."""
    out = np.zeros((n_cam, 3, 3))
    for c in range(1, n_cam):
        out[c] = cov[3 * (c - 1):3 * c, 3 * (c - 1):3 * c]
    return out


def _euler_covariance(rots: np.ndarray, rot_cov: np.ndarray) -> np.ndarray:
    """Propagate the covariance of cameras 1..'s rotation errors to their XYZ Euler angles.

    ``rot_cov`` starts with the ``3 (C - 1)`` rows and columns (radians^2) of the
    rotation errors ``omega`` (``R_hat = exp(omega) R``, from :func:`_bundle_adjust`);
    returns ``(C, 3, 3)`` in degrees^2 (zeros for camera 0), by the Jacobian
    of ``as_euler("xyz")`` with respect to ``omega``.
    """
    out = np.zeros((rots.shape[0], 3, 3))
    for c in range(1, rots.shape[0]):
        rc = Rotation.from_matrix(rots[c])
        jac = _central_jacobian(
            lambda w: (Rotation.from_rotvec(w) * rc).as_euler("xyz", degrees=True), 3, degrees=True)
        out[c] = jac @ rot_cov[3 * (c - 1):3 * c, 3 * (c - 1):3 * c] @ jac.T
    return out
