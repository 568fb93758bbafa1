"""The cyclic feed-forward HMM over walking phases (Izo–Grimson §6).

States are the ``p`` discrete phases of the gait cycle. From state ``i`` the
walker stays (``p_r``), moves on one (``p_n``), two (``p_j``) or three (``p_l``)
states, cyclically. The initial state is uniform. Each state emits one phase
observation per camera; the emission of state ``i`` is the mixture of eq. 9:
``2^c`` diagonal Gaussians whose means put each camera at phase ``i`` or at its
opposite ``i + p/2``.

With equal mixture weights and a shared diagonal covariance the ``2^c``-term
mixture factorises exactly into a product over cameras of two-term mixtures,

    sum_k 2^-c prod_j N(psi_j; f(i, e_j), s^2) = prod_j (N(psi_j; i, s^2) + N(psi_j; i + p/2, s^2)) / 2,

so the emission costs O(c) per state instead of O(2^c). ``opposite_weight``
generalises the equal weights (0.5, the paper) to ``w`` for the opposite phase
and ``1 - w`` for the phase itself; the product form still holds.

Everything is in log space; :func:`viterbi` is a pure function of (log start,
log transition, log emission), as in hmmlearn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["PhaseHMM", "cyclic_transitions", "phase_log_emission", "posterior", "viterbi"]


def cyclic_transitions(n_states: int, probs: tuple[float, ...]) -> np.ndarray:
    """Transition matrix of the cyclic feed-forward model, shape (p, p).

    Parameters
    ----------
    n_states : int
        Number of phases ``p``.
    probs : (p_r, p_n, p_j, p_l) or any tuple of two or more
        Probabilities of staying and of moving 1, 2, 3, ... states on; normalised
        to sum to one (the paper's model has the four).
    """
    probs = np.asarray(probs, dtype=float)
    if probs.ndim != 1 or not 2 <= probs.size or np.any(probs < 0) or probs.sum() <= 0:
        raise ValueError(f"probs must be two or more non-negative numbers (p_r, p_n, p_j, p_l, ...), got {probs}")
    if n_states < max(4, probs.size):
        raise ValueError(f"n_states must be at least 4 and at least len(probs), got {n_states}")
    probs = probs / probs.sum()
    A = np.zeros((n_states, n_states))
    i = np.arange(n_states)
    for step, p in enumerate(probs):
        A[i, (i + step) % n_states] += p
    return A


def _wrapped(d: np.ndarray) -> np.ndarray:
    """Circular difference in cycles, in [-0.5, 0.5)."""
    return (d + 0.5) % 1.0 - 0.5


def phase_log_emission(
    observations: np.ndarray, n_states: int, *, sigma: float, opposite_weight: float = 0.5
) -> np.ndarray:
    """Log-likelihood of phase observations under every state (eq. 9), shape (T, p).

    Parameters
    ----------
    observations : ndarray of shape (T, c)
        Observed phase per frame and camera, in cycles ([0, 1)); NaN where a
        camera has no observation (it contributes nothing).
    n_states : int
        Number of phases ``p``; state ``i`` means phase ``i / p``.
    sigma : float
        Standard deviation of each Gaussian, in cycles.
    opposite_weight : float, optional
        Weight of the opposite-phase component; 0.5 is the paper's equal mixture.
    """
    obs = np.asarray(observations, dtype=float)
    if obs.ndim != 2:
        raise ValueError(f"observations must have shape (T, c), got {obs.shape}")
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    if not 0 <= opposite_weight < 1:
        raise ValueError(f"opposite_weight must lie in [0, 1), got {opposite_weight}")
    missing = np.isnan(obs)
    centres = np.arange(n_states) / n_states
    d = _wrapped(np.where(missing, 0.0, obs)[:, None, :] - centres[None, :, None])  # (T, p, c)
    d_opp = _wrapped(d - 0.5)
    log_norm = -0.5 * np.log(2 * np.pi * sigma**2)
    same = np.log1p(-opposite_weight) - 0.5 * (d / sigma) ** 2
    opp = np.log(opposite_weight) - 0.5 * (d_opp / sigma) ** 2 if opposite_weight > 0 else np.full_like(d, -np.inf)
    per_camera = log_norm + np.logaddexp(same, opp)
    return np.where(missing[:, None, :], 0.0, per_camera).sum(axis=2)


def viterbi(log_start: np.ndarray, log_trans: np.ndarray, log_emission: np.ndarray) -> tuple[float, np.ndarray]:
    """Most likely state path (Viterbi, in log space).

    Parameters
    ----------
    log_start : ndarray of shape (K,)
    log_trans : ndarray of shape (K, K)
        ``log_trans[i, j]`` = log P(j at t+1 | i at t).
    log_emission : ndarray of shape (T, K)

    Returns
    -------
    log_prob : float
        Log joint probability of the path and the observations.
    states : ndarray of shape (T,), int
    """
    log_start = np.asarray(log_start, dtype=float)
    log_trans = np.asarray(log_trans, dtype=float)
    log_emission = np.asarray(log_emission, dtype=float)
    if log_emission.ndim != 2:
        raise ValueError(f"log_emission must have shape (T, K), got {log_emission.shape}")
    T, K = log_emission.shape
    if log_start.shape != (K,) or log_trans.shape != (K, K):
        raise ValueError(f"shapes disagree: start {log_start.shape}, trans {log_trans.shape}, emission {(T, K)}")
    if T == 0:
        return 0.0, np.zeros(0, int)
    delta = log_start + log_emission[0]
    back = np.empty((T, K), int)
    for t in range(1, T):
        scores = delta[:, None] + log_trans  # (from, to)
        back[t] = np.argmax(scores, axis=0)
        delta = scores[back[t], np.arange(K)] + log_emission[t]
    states = np.empty(T, int)
    states[-1] = int(np.argmax(delta))
    for t in range(T - 1, 0, -1):
        states[t - 1] = back[t, states[t]]
    return float(delta[states[-1]]), states


def posterior(log_start: np.ndarray, log_trans: np.ndarray, log_emission: np.ndarray) -> np.ndarray:
    """Posterior probability of every state at every frame (forward-backward, in log space), (T, K).

    Where the Viterbi path says which phase, this says how sure: a frame that
    no camera saw has a flat emission and its posterior spreads over the
    phases the transitions allow.
    """
    log_start, log_trans, log_emission = (np.asarray(a, dtype=float) for a in (log_start, log_trans, log_emission))
    T, K = log_emission.shape
    if T == 0:
        return np.zeros((0, K))
    alpha, beta = np.empty((T, K)), np.zeros((T, K))
    alpha[0] = log_start + log_emission[0]
    for t in range(1, T):
        alpha[t] = np.logaddexp.reduce(alpha[t - 1][:, None] + log_trans, axis=0) + log_emission[t]
    for t in range(T - 2, -1, -1):
        beta[t] = np.logaddexp.reduce(log_trans + (log_emission[t + 1] + beta[t + 1])[None, :], axis=1)
    log_post = alpha + beta
    log_post -= np.logaddexp.reduce(log_post, axis=1, keepdims=True)
    return np.exp(log_post)


@dataclass
class PhaseHMM:
    """Cyclic feed-forward HMM over ``n_states`` walking phases (§6).

    Parameters
    ----------
    n_states : int
        Phases per cycle (the appearance model's 20).
    probs : (p_r, p_n, p_j, p_l)
        Stay / +1 / +2 / +3 probabilities, with p_r < p_n, p_j slightly below
        p_n and p_l slightly below p_j (§6 (2)). The defaults advance 1.72
        states per frame on average (1.29 cycles/s at 15 Hz), a little fast for
        walkers of 0.7–1.1 cycles/s (0.9–1.5 states per frame at 15 Hz); the
        emissions dominate on real windows (docs/ESTIMATION.md).
    sigma : float
        Emission standard deviation in cycles (default: 1.5 states).
    opposite_weight : float
        Weight of the opposite-phase component (0.5 = the paper's equal mixture).

    Attributes
    ----------
    transmat_ : ndarray of shape (n_states, n_states)
    startprob_ : ndarray of shape (n_states,)
    """

    n_states: int = 20
    probs: tuple[float, ...] = (0.1, 0.33, 0.32, 0.25)
    sigma: float = 0.075
    opposite_weight: float = 0.5

    def __post_init__(self) -> None:
        self.transmat_ = cyclic_transitions(self.n_states, self.probs)
        self.startprob_ = np.full(self.n_states, 1.0 / self.n_states)

    def at_fps(self, fps: float, *, tuned_fps: float = 15.0) -> "PhaseHMM":
        """The same walker at another frame rate (``probs`` hold per frame at ``tuned_fps``):
        a 30 fps camera moves 0.86 states per frame on average, not 1.72."""
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"fps must be a positive number, got {fps}")
        return self.scaled(tuned_fps / fps)

    @property
    def mean_advance(self) -> float:
        """Expected states moved on per frame."""
        p = np.asarray(self.probs, float)
        return float((p * np.arange(len(p))).sum() / p.sum())

    def scaled(self, factor: float) -> "PhaseHMM":
        """Every step of ``probs`` times ``factor`` states, its mass split between the two
        nearest whole steps: the mean advance per frame scales by ``factor``, the shape of
        the step distribution is kept."""
        if not (np.isfinite(factor) and factor > 0):
            raise ValueError(f"factor must be a positive number, got {factor}")
        steps = np.arange(len(self.probs)) * factor
        lo = np.floor(steps).astype(int)
        frac = steps - lo
        probs = np.zeros(lo.max() + 2)
        np.add.at(probs, lo, np.asarray(self.probs) * (1 - frac))
        np.add.at(probs, lo + 1, np.asarray(self.probs) * frac)
        probs = probs[:np.flatnonzero(probs > 1e-12).max() + 1]
        return PhaseHMM(self.n_states, tuple(float(p) for p in probs), self.sigma, self.opposite_weight)

    def log_emission(self, observations: np.ndarray) -> np.ndarray:
        """(T, n_states) log-likelihoods of (T, c) phase observations (eq. 9)."""
        return phase_log_emission(observations, self.n_states, sigma=self.sigma, opposite_weight=self.opposite_weight)

    def decode(self, observations: np.ndarray) -> tuple[float, np.ndarray]:
        """Viterbi path of (T, c) phase observations: (log_prob, states (T,))."""
        with np.errstate(divide="ignore"):
            return viterbi(np.log(self.startprob_), np.log(self.transmat_), self.log_emission(observations))
