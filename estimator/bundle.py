"""Levenberg–Marquardt for bundle adjustments, solved by the Schur complement.

A bundle adjustment has a few parameters every residual may touch (cameras,
bone lengths) and many that come in small independent blocks (one frame's
joints): the normal matrix ``J^T J`` is then block-diagonal in the blocks,
and eliminating them (the Schur complement, Triggs et al. 2000, "Bundle
Adjustment — A Modern Synthesis" §6.1) leaves a system the size of the shared
parameters. Each step is exact, so it converges in a few tens of steps where
:func:`scipy.optimize.least_squares` with a sparse Jacobian solves each
trust-region step inexactly (LSMR) and crawls: on 4 cameras x 50 frames of
keypoints it spent 60 evaluations, 0.75 s, for what this does in about 0.1 s.

The damping is Marquardt's (``lambda`` times the normal matrix's diagonal,
floored so that an unobserved parameter stays finite), updated by the gain
ratio as in Nielsen (1999).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse

__all__ = ["LMResult", "levenberg_marquardt"]


@dataclass
class LMResult:
    """What :func:`levenberg_marquardt` found.

    Attributes
    ----------
    x : ndarray
        The parameters at the end.
    fun : ndarray
        The residuals there.
    jac : scipy.sparse.csr_matrix
        The Jacobian there.
    cost : float
        Half the sum of squared residuals.
    nfev : int
        Residual evaluations.
    converged : bool
        Stopped before ``max_nfev``: a good step (gain ratio above 0.25) lowered the cost by
        less than ``ftol`` of it, or no step lowered it at all (the damping grew past 1e16).
    """

    x: np.ndarray
    fun: np.ndarray
    jac: scipy.sparse.csr_matrix
    cost: float
    nfev: int
    converged: bool


def levenberg_marquardt(fun: Callable[[np.ndarray], np.ndarray],
                        jac: Callable[[np.ndarray], scipy.sparse.spmatrix], x0: np.ndarray, *,
                        block_start: int, block_size: int, n_blocks: int, max_nfev: int = 60,
                        ftol: float = 1e-8) -> LMResult:
    """Minimise ``0.5 |fun(x)|^2`` from ``x0`` with Schur-complement Levenberg–Marquardt steps.

    Parameters
    ----------
    fun, jac : callables
        Residuals (M,) and their sparse Jacobian (M, N) at ``x``.
    x0 : ndarray of shape (N,)
    block_start, block_size, n_blocks : int
        ``x[block_start : block_start + block_size * n_blocks]`` are ``n_blocks``
        blocks of ``block_size`` parameters, no residual touching two blocks
        (``J^T J`` block-diagonal there); every other parameter is shared.
    max_nfev, ftol : int, float
        At most ``max_nfev`` steps tried (residual evaluations, and solves that
        failed); stop once a good step lowers the cost by less than ``ftol`` of it.
    """
    x = np.asarray(x0, float).copy()
    n = x.size
    local = np.arange(block_start, block_start + block_size * n_blocks)
    shared = np.setdiff1d(np.arange(n), local)
    r = fun(x)
    cost = 0.5 * float(r @ r)
    J = jac(x).tocsr()
    nfev, lam, nu, converged = 1, 1e-3, 2.0, False
    h = g = None
    while nfev < max_nfev:
        if h is None:  # the normal equations at a new point (kept while steps are rejected)
            h = (J.T @ J).tocsr()
            g = J.T @ r
            diag = h.diagonal()
            damp = np.maximum(diag, 1e-9 * max(float(diag.max()), 1e-300))
        try:
            step = _schur_step(h, g, lam * damp, shared, local, block_size, n_blocks)
        except np.linalg.LinAlgError:
            step = np.full(n, np.nan)
        if np.all(np.isfinite(step)):
            x_new = x + step
            r_new = fun(x_new)
            cost_new = 0.5 * float(r_new @ r_new)
            predicted = 0.5 * float(step @ (lam * damp * step - g))
            rho = (cost - cost_new) / predicted if predicted > 0 and np.isfinite(cost_new) else -1.0
        else:
            rho = -1.0
        nfev += 1  # a failed solve counts too: the loop always ends
        if rho > 0:
            done = rho > 0.25 and cost - cost_new < ftol * cost  # a small decrease alone is no minimum
            x, r, cost = x_new, r_new, cost_new
            J = jac(x).tocsr()
            h = None
            lam = max(lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e-15)
            nu = 2.0
            if done:
                converged = True
                break
        else:
            lam, nu = lam * nu, nu * 2.0
            if lam > 1e16:
                converged = True  # no step lowers the cost: a minimum to working precision
                break
    return LMResult(x, r, J, cost, nfev, converged)


def _schur_step(h: scipy.sparse.csr_matrix, g: np.ndarray, damping: np.ndarray, shared: np.ndarray,
                local: np.ndarray, size: int, n_blocks: int) -> np.ndarray:
    """The damped Gauss–Newton step ``-(H + diag(damping))^-1 g``, the blocks eliminated first."""
    rows = h[shared]
    h_ss = rows[:, shared].toarray() + np.diag(damping[shared])
    h_sl = rows[:, local].toarray().reshape(len(shared), n_blocks, size)
    coo = h[local][:, local].tocoo()
    blocks = np.zeros((n_blocks, size, size))
    same = coo.row // size == coo.col // size
    if not np.all(same[coo.data != 0]):
        raise ValueError("a residual touches two blocks: J^T J is not block-diagonal there")
    blocks[coo.row[same] // size, coo.row[same] % size, coo.col[same] % size] = coo.data[same]
    blocks[:, np.arange(size), np.arange(size)] += damping[local].reshape(n_blocks, size)
    inv = np.linalg.inv(blocks)  # (B, k, k): each block positive definite once damped
    g_s, g_l = g[shared], g[local].reshape(n_blocks, size)
    bd = (h_sl.transpose(1, 0, 2) @ inv).transpose(1, 0, 2).reshape(len(shared), -1)  # H_sl D^-1
    flat = h_sl.reshape(len(shared), -1)
    d_s = np.linalg.solve(h_ss - bd @ flat.T, -g_s + bd @ g_l.ravel())
    d_l = (inv @ (-g_l - (flat.T @ d_s).reshape(n_blocks, size))[..., None])[..., 0]
    out = np.empty(g.size)
    out[shared] = d_s
    out[local] = d_l.ravel()
    return out
