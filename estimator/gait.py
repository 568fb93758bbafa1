"""Walking as smooth periodic joint angles, fitted to real motion capture.

Every angle of :class:`~estimator.skeleton.GaitAngles` is a truncated Fourier
series in the gait phase (DESIGN.md: 0 = right heel strike, 0.5 = left heel
strike). Left and right share one curve half a cycle apart, and the body's
lateral quantities (pelvis yaw and obliquity, thorax yaw, sway) hold only odd
harmonics and the sagittal ones (lean, bounce) only even harmonics, so that the
pose at ``phase + 0.5`` is exactly the mirror image of the pose at ``phase``.

The coefficients are fitted (:func:`fit_gait`) to the CMU walks in
``shared/data/mocap`` and shipped in ``estimator/data/gait_cmu.json``;
``bench/fit_gait.py`` rebuilds that file. A :class:`GaitStyle` scales the
curves: stride, leg lift, arm swing (the parameters Izo–Grimson §7 varied) and
cadence.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields

import numpy as np

from .mocap import Motion
from .skeleton import FULL_JOINT_NAMES, GaitAngles, segment_angles

__all__ = ["GaitModel", "GaitStyle", "fit_gait", "heel_strikes", "load_gait", "motion_angles", "motion_phase"]

GAIT_VERSION = 1
_DATA = os.path.join(os.path.dirname(__file__), "data", "gait_cmu.json")
_J = {name: i for i, name in enumerate(FULL_JOINT_NAMES)}

# Curves per side (left = right half a cycle later) and body curves by parity.
_SIDED = ("thigh", "shank", "foot", "upper_arm", "forearm", "thigh_lat", "shank_lat", "upper_arm_lat", "forearm_lat")
_ODD = ("pelvis_yaw", "pelvis_obliquity", "thorax_yaw", "sway")
_EVEN = ("lean", "bounce")


@dataclass(frozen=True)
class GaitStyle:
    """How a person walks, relative to the fitted average walk.

    Parameters
    ----------
    stride : float
        Scales the swing of the thighs about their mean (and with it step length,
        pelvis rotation and bounce). 1 = as recorded.
    leg_lift : float
        Scales the knee flexion of the swing phase (and the foot's lift).
    arm_swing : float
        Scales the swing of the upper arms and forearms.
    cadence : float
        Gait cycles per second (two steps per cycle); about 0.9–1.1 when walking.
    """

    stride: float = 1.0
    leg_lift: float = 1.0
    arm_swing: float = 1.0
    cadence: float = 0.95

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value < 0 or (f.name == "cadence" and value == 0):
                kind = "positive" if f.name == "cadence" else "non-negative"
                raise ValueError(f"GaitStyle.{f.name} must be a {kind} number, got {value!r}")

    @classmethod
    def random(cls, rng: np.random.Generator | int | None = None) -> "GaitStyle":
        """A plausible walker: each parameter within about ±25% of the average."""
        rng = np.random.default_rng(rng)
        return cls(
            stride=float(rng.uniform(0.8, 1.2)),
            leg_lift=float(rng.uniform(0.75, 1.25)),
            arm_swing=float(rng.uniform(0.5, 1.5)),
            cadence=float(rng.uniform(0.85, 1.1)),
        )


def _design(phase: np.ndarray, harmonics: np.ndarray) -> np.ndarray:
    """Fourier design matrix, shape (N, n_cos + n_sin): cos(2 pi k phase) for each
    harmonic k, then sin(2 pi k phase) for each k > 0."""
    arg = 2 * np.pi * np.asarray(phase, float)[:, None] * harmonics[None, :]
    return np.concatenate([np.cos(arg), np.sin(arg[:, harmonics > 0])], axis=1)


def _harmonics(name: str, n: int) -> np.ndarray:
    k = np.arange(n + 1)
    if name in _ODD:
        return k[k % 2 == 1]
    if name in _EVEN:
        return k[k % 2 == 0]
    return k


@dataclass(frozen=True)
class GaitModel:
    """Fourier coefficients of every gait curve.

    Attributes
    ----------
    coefficients : dict of str to ndarray
        Per curve, coefficients of ``[cos(2 pi k phase)..., sin(2 pi k phase)...]``
        over that curve's harmonics ``k``: all up to ``harmonics`` for the sided
        curves, odd ones for the lateral body curves, even ones for lean and bounce.
    harmonics : int
        Highest harmonic.
    cadence : float
        Mean cycles per second of the recordings.
    sources : tuple of str
        The recordings fitted, and the number of cycles each gave.
    """

    coefficients: dict
    harmonics: int
    cadence: float
    sources: tuple = ()
    version: int = GAIT_VERSION

    def curve(self, name: str, phase: np.ndarray) -> np.ndarray:
        """Evaluate one curve at the given phases, same shape as ``phase``."""
        phase = np.asarray(phase, dtype=float)
        A = _design(phase.ravel(), _harmonics(name, self.harmonics))
        return (A @ self.coefficients[name]).reshape(phase.shape)

    def angles(self, phase: np.ndarray, style: GaitStyle | None = None) -> GaitAngles:
        """Gait angles at the given phases (shape (T,)), scaled by ``style``."""
        style = style or GaitStyle()
        phase = np.atleast_1d(np.asarray(phase, dtype=float)) % 1.0
        sided_phase = np.stack([phase - 0.5, phase], axis=1)  # left, right
        out: dict[str, np.ndarray] = {}
        for name in _SIDED:
            out[name] = self.curve(name, sided_phase)
        for name in _ODD + _EVEN:
            out[name] = self.curve(name, phase)

        def scale(name: str, factor: float, about: str = "mean") -> None:
            grid = self.curve(name, np.linspace(0, 1, 64, endpoint=False))
            ref = grid.mean() if about == "mean" else grid.min()
            out[name] = ref + factor * (out[name] - ref)

        # Stride: thigh swing; the shank and foot follow the thigh so knee and
        # ankle flexion are kept.
        thigh = out["thigh"].copy()
        scale("thigh", style.stride)
        delta = out["thigh"] - thigh
        out["shank"] = out["shank"] + delta
        out["foot"] = out["foot"] + delta
        for name in ("pelvis_yaw", "thorax_yaw", "bounce"):
            scale(name, style.stride)
        # Leg lift: knee flexion (thigh - shank) about its minimum, foot with it.
        knee = out["thigh"] - out["shank"]
        grid_knee = self.curve("thigh", np.linspace(0, 1, 64, endpoint=False)) - self.curve(
            "shank", np.linspace(0, 1, 64, endpoint=False)
        )
        new_knee = grid_knee.min() + style.leg_lift * (knee - grid_knee.min())
        out["shank"] = out["shank"] + (knee - new_knee)
        out["foot"] = out["foot"] + (knee - new_knee)
        for name in ("upper_arm", "forearm"):
            scale(name, style.arm_swing)
        return GaitAngles(**out)

    def to_json(self) -> dict:
        d = asdict(self)
        d["coefficients"] = {k: np.asarray(v).tolist() for k, v in self.coefficients.items()}
        d["sources"] = list(self.sources)
        return d

    @classmethod
    def from_json(cls, d: dict) -> "GaitModel":
        if d.get("version") != GAIT_VERSION:
            raise ValueError(f"gait model version {d.get('version')} is not {GAIT_VERSION}")
        return cls(
            coefficients={k: np.asarray(v, float) for k, v in d["coefficients"].items()},
            harmonics=int(d["harmonics"]),
            cadence=float(d["cadence"]),
            sources=tuple(tuple(s) if isinstance(s, list) else s for s in d["sources"]),
            version=int(d["version"]),
        )


def load_gait(path: str | os.PathLike | None = None) -> GaitModel:
    """The shipped gait model (fitted to CMU walks), or one saved at ``path``."""
    with open(path or _DATA) as fh:
        return GaitModel.from_json(json.load(fh))


def heel_strikes(heading_positions: np.ndarray, side: str) -> np.ndarray:
    """Frame indices (fractional) of heel strikes of one foot.

    Zeni et al. (2008): heel strike is when the foot is furthest in front of the
    pelvis. Refined to sub-frame precision with a parabola through the maximum.

    Parameters
    ----------
    heading_positions : ndarray of shape (T, 20, 3)
        Joint positions in the heading frame.
    side : {"left", "right"}
    """
    if side not in ("left", "right"):
        raise ValueError(f"side must be 'left' or 'right', got {side!r}")
    x = heading_positions[:, _J[f"{side}_ankle"], 0] - heading_positions[:, _J["pelvis"], 0]
    interior = (x[1:-1] > x[:-2]) & (x[1:-1] >= x[2:])
    idx = np.flatnonzero(interior) + 1
    # Keep clear maxima: foot well in front of the pelvis.
    idx = idx[x[idx] > np.percentile(x, 75)]
    a, b, c = x[idx - 1], x[idx], x[idx + 1]
    denom = a - 2 * b + c
    offset = np.where(np.abs(denom) > 1e-12, 0.5 * (a - c) / np.where(denom == 0, 1, denom), 0.0)
    strikes = idx + offset
    # One strike per cycle: drop maxima closer than 60% of the median interval.
    if len(strikes) > 2:
        keep = [strikes[0]]
        gap = np.median(np.diff(strikes))
        for s in strikes[1:]:
            if s - keep[-1] > 0.6 * gap:
                keep.append(s)
        strikes = np.array(keep)
    return strikes


def motion_phase(motion: Motion) -> np.ndarray:
    """Gait phase of every frame of a recording, shape (T,), in [0, 1).

    Linear in time between right heel strikes; before the first and after the
    last, extrapolated with the mean cycle length.
    """
    strikes = heel_strikes(motion.heading_frame(), "right")
    if len(strikes) < 2:
        raise ValueError(f"{motion.source}: fewer than two right heel strikes; is this a walk?")
    t = np.arange(len(motion), dtype=float)
    cycles = np.interp(t, strikes, np.arange(len(strikes)), left=np.nan, right=np.nan)
    period = np.mean(np.diff(strikes))
    before, after = t < strikes[0], t > strikes[-1]
    cycles[before] = (t[before] - strikes[0]) / period
    cycles[after] = len(strikes) - 1 + (t[after] - strikes[-1]) / period
    return cycles % 1.0


def standing_hip_height(heading_positions: np.ndarray) -> float:
    """A subject's hip height standing: thigh + shank + ankle height in stance."""
    P = heading_positions
    thigh = np.median(np.linalg.norm(P[:, _J["left_knee"]] - P[:, _J["left_hip"]], axis=1))
    shank = np.median(np.linalg.norm(P[:, _J["left_ankle"]] - P[:, _J["left_knee"]], axis=1))
    ankle = np.percentile(P[:, [_J["left_ankle"], _J["right_ankle"]], 2], 5)
    return float(thigh + shank + ankle)


def motion_angles(motion: Motion) -> GaitAngles:
    """Gait angles of every frame of a recording (to drive the posecal body)."""
    P = motion.heading_frame()
    return segment_angles(P, standing_hip_height(P))


def fit_gait(motions: list[Motion], *, harmonics: int = 6, trim: float = 3.0) -> GaitModel:
    """Fit the gait curves to recorded walks by least squares.

    Frames outside complete right-heel-strike cycles are dropped; each curve is
    fitted twice, the second time without samples whose residual exceeds
    ``trim`` robust standard deviations (marker glitches).

    Parameters
    ----------
    motions : list of Motion
        Straight walks (at least two right heel strikes each).
    harmonics : int, optional
        Highest harmonic of the Fourier series.
    trim : float, optional
        Outlier threshold in units of 1.4826 * MAD.
    """
    if not motions:
        raise ValueError("fit_gait needs at least one motion")
    phases, samples, sources, periods = [], [], [], []
    for m in motions:
        P = m.heading_frame()
        strikes = heel_strikes(P, "right")
        if len(strikes) < 2:
            raise ValueError(f"{m.source}: fewer than two right heel strikes")
        inside = slice(int(np.ceil(strikes[0])), int(np.floor(strikes[-1])) + 1)
        phases.append(motion_phase(m)[inside])
        samples.append(segment_angles(P[inside], standing_hip_height(P)))
        periods.append(np.diff(strikes) / m.fps)
        sources.append((m.source, len(strikes) - 1))
    phase = np.concatenate(phases)
    coefficients = {}
    for f in fields(GaitAngles):
        name = f.name
        if name == "extra":
            continue
        values = np.concatenate([getattr(s, name) for s in samples])
        if name in _SIDED:  # left sample at phase p is the curve at p - 0.5
            x = np.concatenate([phase - 0.5, phase])
            y = np.concatenate([values[:, 0], values[:, 1]])
        else:
            x, y = phase, values
        A = _design(x % 1.0, _harmonics(name, harmonics))
        keep = np.ones(len(y), bool)
        for _ in range(2):
            coef, *_ = np.linalg.lstsq(A[keep], y[keep], rcond=None)
            resid = y - A @ coef
            mad = 1.4826 * np.median(np.abs(resid[keep] - np.median(resid[keep])))
            keep = np.abs(resid) <= trim * max(mad, 1e-9)
        coefficients[name] = coef
    cadence = float(1.0 / np.mean(np.concatenate(periods)))
    return GaitModel(coefficients=coefficients, harmonics=harmonics, cadence=cadence, sources=tuple(sources))
