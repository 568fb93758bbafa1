"""Baselines for the self-calibration of :mod:`estimator.selfcal` (Wang–Leow §4.1).

Both start from the same centred, normalised rank-3 factorization and the same
rigid links, and finish the same way (Cholesky, cameras, reflection by the
kinematic prior), so that only the way ``Omega`` is found differs:

- :func:`liebowitz_carlsson`: ``Omega`` linear from the rigid-link constraints
  alone (homogeneous least squares); when noise makes it indefinite, Cholesky
  is impossible (the failure §4.1 describes) — counted by the Test 2 script.
- :func:`tresadern_reid`: the camera constraints with both scales unknown
  (equal norms and orthogonal rows, four homogeneous equations for two
  cameras) leave a two-dimensional space of ``Omega^-1``; a nonlinear search
  over its remaining parameter minimises the normalised variance of the link
  lengths.

References
----------
D. Liebowitz and S. Carlsson, "Uncalibrated motion capture exploiting
articulated structure constraints", ICCV 2001.
P. Tresadern and I. Reid, "Uncalibrated and unsynchronized human motion
capture: a stereo factorization approach", CVPR 2004.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.optimize import minimize_scalar

from ._factorization import factorize
from ._selfcal_core import link_rows, sym_bilinear, sym_from_vec, sym_quad
from .selfcal import (
    Link,
    Ratio,
    SelfCalibration,
    _apply_reflection,
    _check_links,
    _check_tracks,
    _mask_unseen,
    _metric,
    _rank_check,
)

__all__ = ["liebowitz_carlsson", "tresadern_reid"]


def _prepare(tracks, links, length_ratios, rank_tol):
    y = _check_tracks(tracks)
    links_, ratios = _check_links(links, length_ratios or ())
    fact = factorize(y)
    t, j = y.shape[1], y.shape[2]
    structure = fact.structure[0].T.reshape(t, j, 3)
    return y, links_, ratios, fact, structure, _rank_check(fact, rank_tol)


def _finish(fact, omega_inv, method, diag) -> SelfCalibration:
    t, j = fact.observed.shape[1:]
    out = _metric(fact.motion[0], fact.structure[0], omega_inv)
    if isinstance(out, str):
        return SelfCalibration.failed(out, method, **diag)
    rots, sc, pts = out
    rots, joints, conf, flip = _apply_reflection(rots, pts.reshape(t, j, 3) * fact.norm)
    diag["reflected"] = flip
    return SelfCalibration(rots, sc, _mask_unseen(joints, fact.observed), None, conf, method, "", diag)


def liebowitz_carlsson(
    tracks: np.ndarray,
    *,
    links: Sequence[Link] | None = None,
    length_ratios: Sequence[Ratio] | None = None,
    on_indefinite: str = "fail",
    rank_tol: float = 1e-6,
) -> SelfCalibration:
    """Liebowitz–Carlsson: ``Omega`` linear from the rigid-link constraints.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, 13, 2)
        As for :func:`estimator.selfcal.self_calibrate`.
    links, length_ratios
        As for :func:`estimator.selfcal.self_calibrate`.
    on_indefinite : {"fail", "clip"}
        When the linear ``Omega`` is not positive definite: return a failed
        result, or clip its eigenvalues to ``1e-3`` of the largest and go on
        (so that an evaluation still gets an estimate). Either way
        ``diagnostics["omega_positive_definite"]`` says what happened.

    Returns
    -------
    SelfCalibration
        ``method = "liebowitz-carlsson"``.

    Notes
    -----
    ``X_tA^T Omega X_tA`` constant over time (and ``= r^2 X_tB^T Omega X_tB``
    for given ratios) is linear and homogeneous in the six entries of
    ``Omega``: the right singular vector of the smallest singular value,
    with the sign that makes its trace positive (Wang–Leow §4.1).
    """
    method = "liebowitz-carlsson"
    if on_indefinite not in ("fail", "clip"):
        raise ValueError(f"on_indefinite must be 'fail' or 'clip', got {on_indefinite!r}")
    y, links_, ratios, fact, structure, reason = _prepare(tracks, links, length_ratios, rank_tol)
    if reason:
        return SelfCalibration.failed(reason, method)
    g = link_rows(structure, fact.observed.all(axis=0), links_, ratios)
    if g.shape[0] < 5:
        return SelfCalibration.failed("fewer than 5 rigid-link constraints", method)
    omega = sym_from_vec(np.linalg.svd(g)[2][-1])
    omega *= np.sign(np.trace(omega)) or 1.0
    w, v = np.linalg.eigh(omega)
    pd = bool(w[0] > 0)
    diag = {"omega_positive_definite": pd, "omega_eigenvalues": w.tolist()}
    if not pd:
        if on_indefinite == "fail":
            return SelfCalibration.failed("the linear Omega is not positive definite", method, **diag)
        w = np.maximum(w, 1e-3 * w[-1])
        omega = (v * w) @ v.T
    return _finish(fact, np.linalg.inv(omega), method, diag)


def tresadern_reid(
    tracks: np.ndarray,
    *,
    links: Sequence[Link] | None = None,
    length_ratios: Sequence[Ratio] | None = None,
    n_grid: int = 72,
    rank_tol: float = 1e-6,
) -> SelfCalibration:
    """Tresadern–Reid: camera constraints first, then a nonlinear search.

    Parameters
    ----------
    tracks : ndarray of shape (C, T, 13, 2)
        As for :func:`estimator.selfcal.self_calibrate`.
    links, length_ratios
        As for :func:`estimator.selfcal.self_calibrate`.
    n_grid : int
        Starting points of the search over the remaining parameter.

    Returns
    -------
    SelfCalibration
        ``method = "tresadern-reid"``.

    Notes
    -----
    Zero skew and unit aspect ratio of every camera (equal row norms,
    orthogonal rows; no scale fixed) are ``2C`` homogeneous linear equations
    in ``Omega^-1``; their two weakest right singular vectors ``N_1, N_2`` span
    the candidates ``Omega^-1 = cos(phi) N_1 + sin(phi) N_2`` (the overall
    scale does not matter). The cost is the normalised variance of the
    squared link lengths, ``sum (l_tk^2 / mean_t l_tk^2 - 1)^2``, plus the
    squared relative error of given ratios; it is minimised over ``phi`` by
    a grid of ``n_grid`` starts and a bounded Brent search around the best.
    """
    method = "tresadern-reid"
    y, links_, ratios, fact, structure, reason = _prepare(tracks, links, length_ratios, rank_tol)
    if reason:
        return SelfCalibration.failed(reason, method)
    motion = fact.motion[0]
    r1, r2 = motion[0::2], motion[1::2]
    rows = np.concatenate([sym_quad(r1) - sym_quad(r2), sym_bilinear(r1, r2)])
    vt = np.linalg.svd(rows)[2]
    n1, n2 = vt[-1], vt[-2]
    valid = fact.observed.all(axis=0)
    ln = np.asarray(links_).reshape(-1, 2)
    q = sym_quad(structure[:, ln[:, 0]] - structure[:, ln[:, 1]])  # (T, K, 6)
    ok = valid[:, ln[:, 0]] & valid[:, ln[:, 1]]
    if ratios:
        la = np.array([r[0] for r in ratios])
        lb = np.array([r[1] for r in ratios])
        r2s = np.array([r[2] ** 2 for r in ratios])
        qa = sym_quad(structure[:, la[:, 0]] - structure[:, la[:, 1]])
        qb = sym_quad(structure[:, lb[:, 0]] - structure[:, lb[:, 1]])
        okr = valid[:, la[:, 0]] & valid[:, la[:, 1]] & valid[:, lb[:, 0]] & valid[:, lb[:, 1]]

    def omega_vec(phi: float) -> np.ndarray | None:
        oi = sym_from_vec(np.cos(phi) * n1 + np.sin(phi) * n2)
        if np.linalg.eigvalsh(oi)[0] <= 0:
            return None
        return np.linalg.inv(oi)[[0, 1, 2, 0, 0, 1], [0, 1, 2, 1, 2, 2]]

    def cost(phi: float) -> float:
        om = omega_vec(phi)
        if om is None:
            return np.inf
        sq = q @ om
        mean = np.where(ok, sq, 0.0).sum(0) / np.maximum(ok.sum(0), 1)
        c = float(np.sum(np.where(ok, sq / mean - 1.0, 0.0) ** 2))
        if ratios:
            c += float(np.sum(np.where(okr, (qa @ om) / (r2s * (qb @ om)) - 1.0, 0.0) ** 2))
        return c

    grid = np.linspace(0.0, 2 * np.pi, n_grid, endpoint=False)
    costs = np.array([cost(p) for p in grid])
    if not np.isfinite(costs).any():
        return SelfCalibration.failed("no positive-definite Omega^-1 satisfies the camera constraints",
                                      method)
    best = grid[int(np.argmin(costs))]
    step = grid[1] - grid[0]
    res = minimize_scalar(cost, bounds=(best - step, best + step), method="bounded")
    phi = float(res.x) if res.fun <= costs.min() else float(best)
    oi = sym_from_vec(np.cos(phi) * n1 + np.sin(phi) * n2)
    return _finish(fact, oi, method, {"phi": phi, "cost": float(min(res.fun, costs.min()))})
