"""A stick-figure stand-in for the rendered examples (tests, benchmarks, evaluation).

Not the paper's body model: a parametric walking skeleton (sinusoidal hip, knee,
shoulder and elbow angles), projected orthographically from (azimuth, elevation)
under the DESIGN.md conventions and drawn with OpenCV as thick lines, a filled
torso and a head disc. It gives :class:`~estimator.examples.Examples` with
exactly known phase, viewpoint and joints so that the appearance model can be
built and tested without the pyrender body renderer.
"""

from __future__ import annotations

import cv2
import numpy as np

from .examples import Examples

# Joint indices in DESIGN.md order.
_HEAD, _LSH, _RSH, _LEL, _REL, _LWR, _RWR, _LHP, _RHP, _LKN, _RKN, _LAN, _RAN = range(13)


def _bump(x, centre, width):
    d = (x - centre + 0.5) % 1.0 - 0.5
    return np.exp(-0.5 * (d / width) ** 2)


def style_table(n_styles: int, *, rng=None) -> np.ndarray:
    """Body styles as rows ``(height_m, width_factor, thickness_factor, stride_factor)``.

    Style 0 is the nominal body; further styles (drawn from ``rng``) vary size,
    build and stride within plausible adult ranges.
    """
    rows = [(1.75, 1.0, 1.0, 1.0)]
    g = np.random.default_rng(rng)
    for _ in range(n_styles - 1):
        rows.append(
            (g.uniform(1.5, 1.95), g.uniform(0.85, 1.2), g.uniform(0.8, 1.3), g.uniform(0.75, 1.2))
        )
    return np.array(rows)


def joints3d(phase: np.ndarray, styles: np.ndarray) -> np.ndarray:
    """3D joints in the person frame (x forward, y left, z up), metres.

    Parameters
    ----------
    phase : ndarray of shape (N,)
    styles : ndarray of shape (N, 4)
        Rows of :func:`style_table`.

    Returns
    -------
    ndarray of shape (N, 18, 3)
        The 13 DESIGN.md joints, then neck, pelvis, (unused), left toe, right toe.
    """
    phase = np.asarray(phase, float)
    hgt, wid, _, stride = (styles[:, i] for i in range(4))
    H = hgt[:, None]
    n = len(phase)
    two_pi = 2 * np.pi
    hip_amp = np.radians(22.0) * stride
    out = np.zeros((n, 18, 3))
    hip_z = 0.53 * hgt
    shoulder_z = 0.82 * hgt
    for side, (hp, kn, an, sh, el, wr, toe, off) in enumerate(
        (
            (_RHP, _RKN, _RAN, _RSH, _REL, _RWR, 17, 0.0),
            (_LHP, _LKN, _LAN, _LSH, _LEL, _LWR, 16, 0.5),
        )
    ):
        sgn = -1.0 if side == 0 else 1.0  # right is -y
        p = (phase - off) % 1.0
        flex = hip_amp * np.cos(two_pi * p)  # forward swing of the thigh
        knee = np.radians(5 + 15 * _bump(p, 0.12, 0.05) + 55 * _bump(p, 0.72, 0.09)) * stride
        thigh, shin = 0.245 * H, 0.25 * H
        hip = np.stack([np.zeros(n), sgn * 0.09 * hgt * wid, hip_z], -1)
        kpos = hip + thigh * np.stack([np.sin(flex), np.zeros(n), -np.cos(flex)], -1)
        a2 = flex - knee
        apos = kpos + shin * np.stack([np.sin(a2), np.zeros(n), -np.cos(a2)], -1)
        tpos = apos + 0.13 * H * np.stack([np.cos(a2 * 0.5), np.zeros(n), np.sin(a2 * 0.5) * 0.3], -1)
        arm = -np.radians(18.0) * stride * np.cos(two_pi * p)  # arms swing against the legs
        elb = np.radians(15 + 15 * (0.5 + 0.5 * np.cos(two_pi * (p - 0.5))))
        sho = np.stack([np.zeros(n), sgn * 0.13 * hgt * wid, shoulder_z], -1)
        epos = sho + 0.186 * H * np.stack([np.sin(arm), sgn * 0.02 * np.ones(n), -np.cos(arm)], -1)
        a3 = arm + elb
        wpos = epos + 0.16 * H * np.stack([np.sin(a3), np.zeros(n), -np.cos(a3)], -1)
        out[:, hp], out[:, kn], out[:, an], out[:, toe] = hip, kpos, apos, tpos
        out[:, sh], out[:, el], out[:, wr] = sho, epos, wpos
    out[:, _HEAD] = np.stack([0.02 * hgt, np.zeros(n), 0.93 * hgt], -1)
    out[:, 13] = np.stack([np.zeros(n), np.zeros(n), 0.86 * hgt], -1)  # neck
    out[:, 14] = np.stack([np.zeros(n), np.zeros(n), hip_z], -1)  # pelvis
    out[:, :, 2] += 0.01 * hgt[:, None] * np.cos(2 * two_pi * phase)[:, None]  # vertical bob
    # Person frame: origin at the centroid of the 13 joints.
    return out - out[:, :13].mean(1, keepdims=True)


def project(points: np.ndarray, azimuth_deg: np.ndarray, elevation_deg: np.ndarray) -> np.ndarray:
    """Orthographic projection to image axes (u right, v down), metres.

    The camera sits at ``(cos el cos az, cos el sin az, sin el)`` from the centroid
    and looks at it; image right is ``up x c``.
    """
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    c = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    right = np.stack([-np.sin(az), np.cos(az), np.zeros_like(az)], -1)
    up = np.cross(c, right)
    u = np.einsum("njk,nk->nj", points, right)
    v = -np.einsum("njk,nk->nj", points, up)
    return np.stack([u, v], -1)


def make_examples(
    phase: np.ndarray,
    azimuth_deg: np.ndarray,
    elevation_deg: np.ndarray,
    style: np.ndarray,
    *,
    styles: np.ndarray,
    crop: tuple[int, int] = (160, 112),
    px_per_m: float = 75.0,
    jitter_px: float = 0.0,
    rng=None,
) -> Examples:
    """Draw stick-figure examples.

    Parameters
    ----------
    phase, azimuth_deg, elevation_deg, style : ndarray of shape (N,)
    styles : ndarray of shape (S, 4)
        From :func:`style_table`; ``style`` indexes its rows.
    crop : (int, int)
        Silhouette (height, width).
    px_per_m : float
        Image scale; the body centroid sits at the crop centre.
    jitter_px : float
        Standard deviation of a random translation of each example (pixels).
    """
    g = np.random.default_rng(rng)
    phase = np.asarray(phase, float)
    st = styles[np.asarray(style)]
    pts = joints3d(phase, st)
    uv = project(pts, np.asarray(azimuth_deg, float), np.asarray(elevation_deg, float))
    h, w = crop
    uv = uv * px_per_m + np.array([w / 2.0, h / 2.0])
    if jitter_px:
        uv = uv + g.normal(0.0, jitter_px, (len(uv), 1, 2))
    sil = np.zeros((len(uv), h, w), np.uint8)
    shift = 4
    fp = np.round(uv * (1 << shift)).astype(np.int32)
    thick = st[:, 2] * st[:, 0] * px_per_m
    for i in range(len(uv)):
        q = fp[i]
        t = thick[i]
        img = sil[i]
        torso = q[[_LSH, _RSH, _RHP, _LHP]]
        cv2.fillConvexPoly(img, cv2.convexHull(torso), 255, cv2.LINE_8, shift)
        for a, b, f in (
            (_LHP, _LKN, 0.075), (_RHP, _RKN, 0.075), (_LKN, _LAN, 0.055), (_RKN, _RAN, 0.055),
            (_LAN, 16, 0.04), (_RAN, 17, 0.04), (_LSH, _LEL, 0.05), (_RSH, _REL, 0.05),
            (_LEL, _LWR, 0.04), (_REL, _RWR, 0.04), (13, _HEAD, 0.06), (_LSH, _RHP, 0.09),
            (_RSH, _LHP, 0.09), (_LHP, _RHP, 0.1),
        ):
            cv2.line(img, tuple(q[a]), tuple(q[b]), 255, max(1, int(round(f * t))), cv2.LINE_8, shift)
        cv2.circle(img, tuple(q[_HEAD] - np.array([0, int(0.02 * t * 16)])), int(0.065 * t * 16), 255, -1, cv2.LINE_8, shift)
    return Examples(
        silhouettes=sil,
        joints2d=uv[:, :13].astype(np.float32),
        phase=phase,
        azimuth_deg=np.asarray(azimuth_deg, float),
        elevation_deg=np.asarray(elevation_deg, float),
        style=np.asarray(style, int),
    )


def grid_examples(
    *,
    n_phases: int = 20,
    azimuth_step: float = 5.0,
    elevations: np.ndarray | None = None,
    n_styles: int = 1,
    style_rng=0,
    **kwargs,
) -> Examples:
    """The paper's grid (20 phases x 72 azimuths x 12 elevations) for each style."""
    if elevations is None:
        elevations = np.arange(-20.0, 36.0, 5.0)
    az = np.arange(0.0, 360.0, azimuth_step)
    ph = np.arange(n_phases) / n_phases
    st = np.arange(n_styles)
    P, A, E, S = np.meshgrid(ph, az, elevations, st, indexing="ij")
    styles = style_table(n_styles, rng=style_rng)
    return make_examples(P.ravel(), A.ravel(), E.ravel(), S.ravel(), styles=styles, **kwargs)
