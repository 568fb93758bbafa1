"""Tomasi–Kanade rank-3 factorization of 2D joint tracks, with missing entries.

Private helper of :mod:`estimator.selfcal` and :mod:`estimator.selfcal_baselines`.

The measurement matrix of Wang–Leow eq. 4 stacks the ``u`` and ``v`` rows of
every camera (2C rows) over the ``T * J`` joint observations (columns). After
each frame's centroid is removed from each row, an affine reconstruction is
its best rank-3 approximation ``W ~ M_hat @ P_hat``. Missing joints (NaN) are
filled in by alternating the rank-3 fit and re-imputation (an EM-style
low-rank completion) until the imputed values stop moving.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Factorization", "factorize", "noise_sigma"]


@dataclass(frozen=True)
class Factorization:
    """An affine reconstruction of normalised tracks.

    Attributes
    ----------
    motion : ndarray of shape (G, 2C, 3)
        ``M_hat`` of eq. 4, rows ``u_c, v_c`` per camera; ``G = 1`` for one
        factorization of the whole sequence, ``G = T`` for one per frame.
    structure : ndarray of shape (G, 3, N)
        ``P_hat`` of eq. 4; ``N = T * J`` (``G = 1``) or ``J`` (``G = T``).
    singular_values : ndarray of shape (G, min(2C, N))
        Of the centred, normalised measurement matrix (after imputation).
    norm : float
        The tracks were divided by this (RMS of the centred observations);
        multiply reconstructed lengths by it to get pixels.
    centroids : ndarray of shape (C, T, 2)
        Per-camera, per-frame centroid of the (imputed) joints, in pixels.
    observed : ndarray of shape (C, T, J), bool
        Which joints were observed.
    iterations : int
        Imputation iterations used (0 when nothing was missing).
    """

    motion: np.ndarray
    structure: np.ndarray
    singular_values: np.ndarray
    norm: float
    centroids: np.ndarray
    observed: np.ndarray
    iterations: int


def _rank3(w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched rank-3 factorization of ``w`` (G, R, N): (M, P, singular values)."""
    u, s, vt = np.linalg.svd(w, full_matrices=False)
    root = np.sqrt(s[:, :3])
    return u[:, :, :3] * root[:, None, :], root[:, :, None] * vt[:, :3, :], s


def _ridge(a: np.ndarray) -> np.ndarray:
    """``a + eps I`` for a stack of 3x3 normal matrices, ``eps`` = 1e-12 of the trace: a
    frame that some camera missed whole has rank < 3 on its own (``per_frame``) and
    would make them singular; elsewhere the change is below rounding."""
    eps = 1e-12 * np.trace(a, axis1=1, axis2=2) + 1e-300
    return a + eps[:, None, None] * np.eye(3)


def factorize(
    tracks: np.ndarray,
    *,
    per_frame: bool = False,
    max_iter: int = 1000,
    tol: float = 1e-8,
    relax: float = 1.8,
) -> Factorization:
    """Centre, normalise and factorize 2D tracks (Tomasi–Kanade, eq. 4).

    Parameters
    ----------
    tracks : ndarray of shape (C, T, J, 2)
        Image coordinates ``(u, v)``; NaN marks a missing joint.
    per_frame : bool
        Factorize each frame's ``2C x J`` matrix on its own (the changing-scale
        extension of §4.3) instead of the whole ``2C x TJ`` matrix (§4.2).
    max_iter, tol : int, float
        Imputation stops after ``max_iter`` rounds or when the RMS change of
        the imputed entries falls below ``tol`` (in normalised units).
    relax : float
        Over-relaxation of the imputation step (1 = plain EM). A joint seen by
        one camera only has a free depth, so the completion is not unique;
        any fixed point gives the same rank-3 fit of the observed entries.

    Returns
    -------
    Factorization
    """
    c, t, j, _ = tracks.shape
    observed = np.isfinite(tracks).all(axis=-1)
    # (2C, T, J): rows u_0, v_0, u_1, v_1, ...
    w = np.moveaxis(tracks, 3, 1).reshape(2 * c, t, j).astype(float)
    missing = ~np.repeat(observed, 2, axis=0)
    any_missing = bool(missing.any())
    if any_missing:
        counts = (~missing).sum(axis=2, keepdims=True)
        frame_mean = np.where(counts > 0, np.nansum(np.where(missing, 0.0, w), axis=2,
                                                    keepdims=True) / np.maximum(counts, 1), np.nan)
        # Cameras that saw nothing in a frame: the camera's mean centroid.
        row_mean = np.nanmean(frame_mean, axis=1, keepdims=True)
        frame_mean = np.where(np.isfinite(frame_mean), frame_mean, row_mean)
        w = np.where(missing, frame_mean, w)
    centroids = w.mean(axis=2, keepdims=True)
    centred = w - centroids
    norm = float(np.sqrt(np.mean(centred[~missing] ** 2)))
    if not np.isfinite(norm) or norm <= 0:
        norm = 1.0
    w = w / norm

    def split(x: np.ndarray) -> np.ndarray:
        return x.transpose(1, 0, 2) if per_frame else x.reshape(1, 2 * c, t * j)

    def merge(x: np.ndarray) -> np.ndarray:
        return x.transpose(1, 0, 2) if per_frame else x.reshape(2 * c, t, j)

    iterations = 0
    centroids = w.mean(axis=2, keepdims=True)
    m, p, s = _rank3(split(w - centroids))
    while any_missing and iterations < max_iter:
        # One alternating least-squares step on the filled matrix (same fixed
        # point as re-running the SVD, at a fraction of the cost).
        wc = split(w - centroids)
        p = np.linalg.solve(_ridge(np.swapaxes(m, 1, 2) @ m), np.swapaxes(m, 1, 2) @ wc)
        m = np.swapaxes(np.linalg.solve(_ridge(p @ np.swapaxes(p, 1, 2)), p @ np.swapaxes(wc, 1, 2)), 1, 2)
        fit = merge(m @ p) + centroids
        step = fit[missing] - w[missing]
        change = np.sqrt(np.mean(step**2))
        w[missing] += relax * step
        centroids = w.mean(axis=2, keepdims=True)
        iterations += 1
        if change < tol:
            break
    if any_missing:
        m, p, s = _rank3(split(w - centroids))
    cen = (centroids[:, :, 0] * norm).reshape(c, 2, t).transpose(0, 2, 1)
    return Factorization(m, p, s, norm, cen, observed, iterations)


def noise_sigma(fact: Factorization) -> float:
    """Per-coordinate 2D noise std estimated from the rank-3 residual, normalised units.

    Fixed cameras make the centred ``2C x TJ`` measurement matrix exactly rank 3
    (one ``2C x J`` matrix per frame for ``per_frame=True``), so whatever the
    rank-3 fit leaves is noise. For i.i.d. noise of variance ``sigma^2`` the
    best rank-r fit of an ``m x n`` matrix leaves ``sigma^2 (m - r)(n - r)``
    (the residual's degrees of freedom, to first order); centring each frame
    removes one column per frame (``n = T (J - 1)``), and imputed entries are
    fitted exactly (the count is scaled by the observed fraction). Zero on
    noise-free tracks.
    """
    sv = fact.singular_values
    g, rows = sv.shape[0], fact.motion.shape[1]
    _, t, j = fact.observed.shape
    cols = (j - 1) if g == t and g > 1 else t * (j - 1)
    dof = g * max(rows - 3, 0) * max(cols - 3, 0) * float(fact.observed.mean())
    if dof <= 0:
        return 0.0
    return float(np.sqrt(np.sum(sv[:, 3:] ** 2) / dof))
