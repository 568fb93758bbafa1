"""Shared algebra of the self-calibration methods (private).

Symmetric 3x3 matrices are handled as 6-vectors ``[s00, s11, s22, s01, s02, s12]``
so that quadratic and bilinear forms become dot products: ``a^T S a =
sym_quad(a) @ vec(S)`` and ``a^T S b = sym_bilinear(a, b) @ vec(S)``. That is
what makes the camera constraints (Wang–Leow eqs. 7–11) linear in
``Omega^-1`` and the rigid-link constraints linear in ``Omega``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .joints import JOINT_INDEX

# Reflection D = diag(1, 1, -1) in camera 0's frame: the depth reversal
# (Necker) ambiguity of scaled orthographic views.
DEPTH_FLIP = np.diag([1.0, 1.0, -1.0])

_TRI_I = np.array([0, 1, 2, 0, 0, 1])
_TRI_J = np.array([0, 1, 2, 1, 2, 2])


def sym_quad(a: np.ndarray) -> np.ndarray:
    """(..., 3) -> (..., 6) with ``a^T S a = sym_quad(a) @ vec(S)``."""
    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    return np.stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z], axis=-1)


def sym_bilinear(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 3), (..., 3) -> (..., 6) with ``a^T S b = sym_bilinear(a, b) @ vec(S)``."""
    return np.stack(
        [
            a[..., 0] * b[..., 0],
            a[..., 1] * b[..., 1],
            a[..., 2] * b[..., 2],
            a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0],
            a[..., 0] * b[..., 2] + a[..., 2] * b[..., 0],
            a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1],
        ],
        axis=-1,
    )


def sym_from_vec(v: np.ndarray) -> np.ndarray:
    """(..., 6) -> (..., 3, 3) symmetric."""
    out = np.empty(v.shape[:-1] + (3, 3))
    out[..., _TRI_I, _TRI_J] = v
    out[..., _TRI_J, _TRI_I] = v
    return out


def vec_from_sym(s: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 6)."""
    return s[..., _TRI_I, _TRI_J]


def adj3(m: np.ndarray) -> np.ndarray:
    """Adjugate of (..., 3, 3) matrices (``adj(M) = det(M) inv(M)``)."""
    a = m
    out = np.empty_like(a)
    out[..., 0, 0] = a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1]
    out[..., 0, 1] = a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2]
    out[..., 0, 2] = a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1]
    out[..., 1, 0] = a[..., 1, 2] * a[..., 2, 0] - a[..., 1, 0] * a[..., 2, 2]
    out[..., 1, 1] = a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0]
    out[..., 1, 2] = a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2]
    out[..., 2, 0] = a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0]
    out[..., 2, 1] = a[..., 0, 1] * a[..., 2, 0] - a[..., 0, 0] * a[..., 2, 1]
    out[..., 2, 2] = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    return out


def camera_constraint_rows(motion: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera constraints on ``vec(Omega^-1)``, Wang–Leow eqs. 7–11.

    Parameters
    ----------
    motion : ndarray of shape (..., 2C, 3)
        Affine camera rows ``M_hat`` (u and v row per camera).

    Returns
    -------
    a : ndarray of shape (..., 2C + 1, 6)
    b : ndarray of shape (..., 2C + 1)
        ``a @ vec(Omega^-1) = b``: camera 0 has unit, orthogonal rows (eqs. 7–9,
        which fixes the scale: camera 0's scale is absorbed into ``U^-1``);
        every other camera has equal-norm, orthogonal rows (eqs. 10–11).
    """
    r1, r2 = motion[..., 0::2, :], motion[..., 1::2, :]
    first = np.stack(
        [sym_quad(r1[..., 0, :]), sym_quad(r2[..., 0, :]), sym_bilinear(r1[..., 0, :], r2[..., 0, :])],
        axis=-2,
    )
    eq_norm = sym_quad(r1[..., 1:, :]) - sym_quad(r2[..., 1:, :])
    eq_orth = sym_bilinear(r1[..., 1:, :], r2[..., 1:, :])
    rest = np.stack([eq_norm, eq_orth], axis=-2).reshape(motion.shape[:-2] + (-1, 6))
    a = np.concatenate([first, rest], axis=-2)
    b = np.zeros(a.shape[:-1])
    b[..., 0] = 1.0
    b[..., 1] = 1.0
    return a, b


def nearest_scaled_rotation(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest scaled orthographic camera to affine rows.

    Parameters
    ----------
    rows : ndarray of shape (..., 2, 3)

    Returns
    -------
    rotation : ndarray of shape (..., 3, 3)
        Rows: the image u axis, the image v axis, the viewing direction
        ``u x v``; det = +1.
    scale : ndarray of shape (...)
        Mean of the two singular values of ``rows``.
    """
    u, s, vt = np.linalg.svd(rows, full_matrices=False)
    orth = u @ vt
    third = np.cross(orth[..., 0, :], orth[..., 1, :])
    return np.concatenate([orth, third[..., None, :]], axis=-2), s.mean(axis=-1)


def poly_interp(values: np.ndarray, nodes: np.ndarray) -> np.ndarray:
    """Exact polynomial coefficients (highest first) through ``len(nodes)`` samples.

    ``values`` has shape (len(nodes), ...); returns (len(nodes), ...).
    """
    vander = np.vander(nodes, len(nodes))
    flat = values.reshape(len(nodes), -1)
    return np.linalg.solve(vander, flat).reshape(values.shape)


def link_rows(
    structure: np.ndarray,
    valid: np.ndarray,
    links: Sequence[tuple[int, int]],
    ratios: Sequence[tuple[tuple[int, int], tuple[int, int], float]],
    *,
    constant_length: bool = True,
    pairing: str = "mean",
    normalise: bool = False,
) -> np.ndarray:
    """Rigid-link constraints on ``vec(Omega)`` (Wang–Leow §4.1).

    Parameters
    ----------
    structure : ndarray of shape (T, J, 3)
        Affine 3D joints ``P_hat``.
    valid : ndarray of shape (T, J), bool
        Joints observed in every camera.
    links : sequence of (int, int)
        Joint pairs whose distance is constant over time.
    ratios : sequence of ((int, int), (int, int), float)
        ``(link_a, link_b, r)`` with ``|link_a| = r |link_b|`` in every frame.
    constant_length : bool
        Add the second kind of constraint (constant length over time).
    pairing : {"mean", "consecutive"}
        ``"consecutive"``: ``X_tA^T Omega X_tA - X_{t+1,A}^T Omega X_{t+1,A} = 0``
        between consecutive valid frames, as written in §4.1. ``"mean"``: each
        frame against the link's mean over frames, ``q(X_tA) - mean_t q(X_tA)``;
        the same set of equations up to linear combination (each consecutive
        difference is the difference of two centred rows), but far better
        conditioned in least squares (docs/SELFCAL.md).
    normalise : bool
        Divide each link's rows by its mean squared affine length.

    Returns
    -------
    ndarray of shape (M, 6)
        Rows ``g`` with ``g @ vec(Omega) = 0`` in the noise-free case.
    """
    rows = []
    t = structure.shape[0]
    if constant_length and len(links):
        ln = np.asarray(links)
        x = structure[:, ln[:, 0]] - structure[:, ln[:, 1]]  # (T, K, 3)
        ok = valid[:, ln[:, 0]] & valid[:, ln[:, 1]]  # (T, K)
        q = sym_quad(x)
        if normalise:
            sq = np.where(ok, np.sum(x * x, axis=-1), 0.0).sum(0) / np.maximum(ok.sum(0), 1)
            q = q / np.where(sq > 0, sq, 1.0)[None, :, None]
        if pairing == "consecutive":
            # Next valid frame of each link (T if none).
            idx = np.where(ok, np.arange(t)[:, None], t)
            later = np.minimum.accumulate(idx[::-1], axis=0)[::-1]
            nxt = np.concatenate([later[1:], np.full((1, ok.shape[1]), t)], axis=0)
            pair = ok & (nxt < t)
            f, k = np.nonzero(pair)
            rows.append(q[nxt[f, k], k] - q[f, k])
        else:
            n = ok.sum(0)
            mean = np.where(ok[..., None], q, 0.0).sum(0) / np.maximum(n, 1)[:, None]
            use = ok & (n >= 2)[None, :]
            rows.append((q - mean[None])[use])
    if len(ratios):
        la = np.array([r[0] for r in ratios])
        lb = np.array([r[1] for r in ratios])
        r2 = np.array([float(r[2]) ** 2 for r in ratios])
        xa = structure[:, la[:, 0]] - structure[:, la[:, 1]]
        xb = structure[:, lb[:, 0]] - structure[:, lb[:, 1]]
        ok = valid[:, la[:, 0]] & valid[:, la[:, 1]] & valid[:, lb[:, 0]] & valid[:, lb[:, 1]]
        g = sym_quad(xa) - r2[None, :, None] * sym_quad(xb)
        rows.append(g[ok])
    if not rows:
        return np.zeros((0, 6))
    return np.concatenate(rows, axis=0)


_KNEES = [(JOINT_INDEX[f"{s}_hip"], JOINT_INDEX[f"{s}_knee"], JOINT_INDEX[f"{s}_ankle"])
          for s in ("left", "right")]
_ELBOWS = [(JOINT_INDEX[f"{s}_shoulder"], JOINT_INDEX[f"{s}_elbow"], JOINT_INDEX[f"{s}_wrist"])
           for s in ("left", "right")]


def kinematic_reflection(joints: np.ndarray) -> tuple[bool, float]:
    """Decide the depth-reversal ambiguity from how knees and elbows bend.

    A knee bends so that it sits in front of the hip–ankle line, an elbow so
    that it sits behind the shoulder–wrist line; "front" is ``left x up`` of the
    torso (left from the right to the left hip and shoulder, up from the hips
    to the shoulders). Reflecting the structure in depth reverses the sign of
    every such vote, so the votes decide.

    Parameters
    ----------
    joints : ndarray of shape (T, 13, 3)
        Metric joints (NaN allowed).

    Returns
    -------
    flip : bool
        True when the structure should be reflected (votes are against it).
    confidence : float
        Weighted share of the votes, in [0.5, 1], that agree with the chosen
        orientation (weights = how far the joint is off the line); 0.5 means
        no information (straight limbs, or votes split evenly).
    """
    left = (joints[:, JOINT_INDEX["left_hip"]] - joints[:, JOINT_INDEX["right_hip"]]
            + joints[:, JOINT_INDEX["left_shoulder"]] - joints[:, JOINT_INDEX["right_shoulder"]])
    up = (joints[:, JOINT_INDEX["left_shoulder"]] + joints[:, JOINT_INDEX["right_shoulder"]]
          - joints[:, JOINT_INDEX["left_hip"]] - joints[:, JOINT_INDEX["right_hip"]])
    front = np.cross(left, up)
    front /= np.linalg.norm(front, axis=-1, keepdims=True) + 1e-300
    tri = np.array(_KNEES + _ELBOWS)  # (4, 3)
    off = joints[:, tri[:, 1]] - 0.5 * (joints[:, tri[:, 0]] + joints[:, tri[:, 2]])  # (T, 4, 3)
    sign = np.array([1.0, 1.0, -1.0, -1.0])
    votes = sign * np.einsum("tkd,td->tk", off, front)
    votes = votes[np.isfinite(votes)]
    total = np.abs(votes).sum()
    if total <= 0:
        return False, 0.5
    agree = votes.clip(min=0).sum() / total
    return bool(agree < 0.5), float(max(agree, 1.0 - agree))


def proper_rotations(r: np.ndarray, atol: float = 1e-6) -> bool:
    """Whether every (..., 3, 3) matrix of ``r`` is a proper rotation (orthonormal, det = +1)."""
    return bool(np.allclose(r @ np.swapaxes(r, -1, -2), np.eye(3), atol=atol)
                and np.allclose(np.linalg.det(r), 1.0, atol=atol))


def geodesic_deg(r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """SO(3) geodesic angle between rotations, degrees; shapes (..., 3, 3)."""
    rel = np.swapaxes(r1, -1, -2) @ r2
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def triangulate(y: np.ndarray, observed: np.ndarray, rots: np.ndarray, scales: np.ndarray,
                 centroids: np.ndarray) -> np.ndarray:
    """Joints (T, J, 3) in camera 0's frame that best reproject, by linear least squares,
    through scaled orthographic cameras ``s_c (R_c X)_{uv} + centroid_ct``; ``scales`` (C,), or
    (C, T) for a scale per camera and frame (weak perspective)."""
    w = observed[..., None].astype(float)  # (C, T, J, 1)
    obs = np.where(observed[..., None], y - centroids[:, :, None, :], 0.0)  # (C, T, J, 2)
    s = np.asarray(scales, float)
    s = np.broadcast_to(s[:, None] if s.ndim == 1 else s, y.shape[:2])
    a = s[:, :, None, None] * rots[:, None, :2, :]  # (C, T, 2, 3)
    normal = np.einsum("ctjk,ctka,ctkb->tjab", np.repeat(w, 2, axis=-1), a, a)
    rhs = np.einsum("ctjk,ctka->tja", obs, a)
    eps = 1e-9 * np.trace(normal, axis1=2, axis2=3)[..., None, None] + 1e-12
    x = np.linalg.solve(normal + eps * np.eye(3), rhs[..., None])[..., 0]
    return x - x.mean(axis=1, keepdims=True)
