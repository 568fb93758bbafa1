"""2D posture from a silhouette by modified nonparametric belief propagation (Wang–Leow §2–3).

The body is a tree of parts (Wang–Leow §2, Fig. 1d): the torso at the root,
the head, upper arms and thighs attached to it, forearms and shins to those.
Each part's pose ``x_i`` is a 2D position, an orientation and a projected
length (its size, person-specific and foreshortened, is free within bounds);
the torso carries its centre, axis, length and signed shoulder and hip
half-widths. Beliefs are weighted particle sets (nonparametric), messages
are kernel sums over the sender's particles (eq. 2), beliefs their product
with the observation function (eq. 3).

What makes it the paper's *modified* NBP:

- **Occlusion** (eq. 1–3): the observation function ``phi_i(x_i, X_-i, z)``
  scores part *i* drawn together with the other parts' previous estimates
  ``X_-i^(n-1)``: pixels the others already cover count for nothing, so a
  part behind another is scored on what is really visible, and an arm over
  the torso is neither rewarded nor punished (the prior decides) rather than
  pulled onto the torso's edge.
- **Scale**: every part's projected length is sampled (0.3–1.1 times its
  model length at the walker's image height), so a walker nearer or farther,
  or taller or shorter, than the model is followed part by part; the widths
  are the person's, read off the silhouettes first (:func:`person_widths`).
- **Annealing**: the observation enters as ``phi^(1/tau_n)`` with a
  temperature ``tau_n`` decreasing over the iterations (the paper's
  decreasing factor lambda), and the particle perturbations shrink with it.

Choices where the paper defers to its reference [13] (not available):

- observation: with ``G = 0`` where another part is drawn, ``+1`` on the
  silhouette, ``-1`` off it, ``phi_i = exp(sum of G over part i / T)``, the
  change part *i* makes to the symmetric difference between the drawn body
  and the silhouette (its overlap and its edges together); parts are
  capsules (thick segments, the fast OpenCV drawing of DESIGN.md), scored
  on a grid of points inside them (vectorised, no drawing per candidate);
- articulation ``psi_ij``: a Gaussian on the gap between a child's proximal
  end and the parent's attachment point, its width (``joint_sigma``, of the
  walker's height) shrinking over the iterations with the temperature: the
  paper's lambda modifies the potential functions, and a loose joint early
  lets a limb swing before the part hanging from it has followed;
- a weak unary prior (``prior_sigma`` of the height) around the starting
  posture (Izo–Grimson's model placement): a silhouette cannot tell where
  an arm in front of the torso is, the gait model can;
- messages are computed at the receiver's particles, with the sender's
  belief weights divided by the message the receiver last sent it (the
  usual particle-BP estimate of eq. 2's product over ``Gamma(i) \\ j``);
  particles are proposed from the perturbed current belief and, for a
  child, half of them at the parent's attachment point.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import cv2
import numpy as np

from .joints import JOINT_INDEX, N_JOINTS
from .occlusion import whole_height

if TYPE_CHECKING:
    from .pipeline import WalkEstimate

__all__ = ["MNBPConfig", "Posture2D", "PARTS_2D", "estimate_posture2d", "estimate_postures2d", "measure_postures",
           "posture_sequence", "posture_sequences"]

_J = JOINT_INDEX


@dataclass(frozen=True)
class _Part:
    name: str
    parent: str | None
    distal: str  # the joint at its far end (the head joint for the head)
    length: float  # model length, fraction of stature
    width: float  # capsule diameter, fraction of stature
    extend: float = 1.0  # the capsule runs past the distal joint (hand, foot) by this factor


PARTS_2D: tuple[_Part, ...] = (
    _Part("torso", None, "", 0.29, 0.11),
    _Part("head", "torso", "head", 0.12, 0.12),
    _Part("left_upper_arm", "torso", "left_elbow", 0.172, 0.06),
    _Part("right_upper_arm", "torso", "right_elbow", 0.172, 0.06),
    _Part("left_forearm", "left_upper_arm", "left_wrist", 0.157, 0.045, 1.45),
    _Part("right_forearm", "right_upper_arm", "right_wrist", 0.157, 0.045, 1.45),
    _Part("left_thigh", "torso", "left_knee", 0.245, 0.09),
    _Part("right_thigh", "torso", "right_knee", 0.245, 0.09),
    _Part("left_shin", "left_thigh", "left_ankle", 0.246, 0.06, 1.12),
    _Part("right_shin", "right_thigh", "right_ankle", 0.246, 0.06, 1.12),
)
"""The body parts of the 2D graph (Wang–Leow Fig. 1d), root first; lengths and
widths as fractions of stature (skeleton.py's ratios, body.py's girths)."""

_INDEX = {p.name: i for i, p in enumerate(PARTS_2D)}
MODEL_WIDTHS = np.array([p.width for p in PARTS_2D])
MODEL_WIDTHS.flags.writeable = False
_EDGES = tuple((_INDEX[p.parent], i) for i, p in enumerate(PARTS_2D) if p.parent)
_NEIGHBOURS = {i: [k for e in _EDGES for k in e if i in e and k != i] for i in range(len(PARTS_2D))}
# The joint of the parent a child hangs from: "neck" = the shoulders' midpoint.
_ATTACH = {"head": "neck", "left_upper_arm": "left_shoulder", "right_upper_arm": "right_shoulder",
           "left_thigh": "left_hip", "right_thigh": "right_hip"}


@dataclass(frozen=True)
class MNBPConfig:
    """mNBP parameters; lengths are fractions of the walker's image height."""

    n_particles: int = 64
    n_iterations: int = 6
    temperature: tuple[float, float] = (0.004, 0.002)  # first / last, times height^2
    joint_sigma: tuple[float, float] = (0.08, 0.015)  # first / last iteration
    prior_sigma: float = 0.12
    torso_prior_sigma: float = 0.003  # see _prior_energy
    along_sigma: float | None = None  # e.g. 0.02: limbs held along their start's axis (see _prior_energy)
    step_position: tuple[float, float] = (0.03, 0.006)
    step_angle_deg: tuple[float, float] = (20.0, 4.0)
    step_length: tuple[float, float] = (0.12, 0.03)  # fraction of the part's model length
    length_range: tuple[float, float] = (0.3, 1.1)
    explore: float = 0.5  # share of a limb's proposals with a fresh angle ...
    explore_deg: float = 90.0  # ... within this of the current best (shrinking to 0 by the end)
    fit_widths: bool = True  # the person's own limb widths (person_widths) instead of the model's
    seed: int = 0


@dataclass
class Posture2D:
    """The measured 2D posture on one silhouette: 13 joints in its crop's pixels."""

    joints: np.ndarray  # (13, 2)
    score: float  # sum of G over the whole drawn body / silhouette area (1 = perfect)
    states: list[np.ndarray] = field(repr=False, default_factory=list)  # per part, its pose


# --------------------------------------------------------------------- geometry


def _unit(angle: np.ndarray) -> np.ndarray:
    return np.stack([np.cos(angle), np.sin(angle)], -1)


def _torso_points(x: np.ndarray) -> dict[str, np.ndarray]:
    """Torso state(s) ``(cx, cy, angle, length, s_n, s_u, h_n, h_u)`` -> its joints.

    ``angle`` is the direction hip-mid -> shoulder-mid, ``length`` their
    distance; the left shoulder is ``shoulder-mid + s_n * normal + s_u * axis``
    and the right one its opposite (likewise the hips with ``h``): any four
    points with those midpoints, since a projected shoulder line need not be
    square to the spine.
    """
    c, ang, ln = x[..., :2], x[..., 2], x[..., 3]
    u = _unit(ang)
    n = np.stack([u[..., 1], -u[..., 0]], -1)
    sm, hm = c + 0.5 * ln[..., None] * u, c - 0.5 * ln[..., None] * u
    s_off = x[..., 4:5] * n + x[..., 5:6] * u
    h_off = x[..., 6:7] * n + x[..., 7:8] * u
    return {"neck": sm, "hips_mid": hm, "left_shoulder": sm + s_off, "right_shoulder": sm - s_off,
            "left_hip": hm + h_off, "right_hip": hm - h_off}


def _limb_end(x: np.ndarray, factor: float = 1.0) -> np.ndarray:
    """Limb state(s) ``(px, py, angle, length)`` -> the distal point (times ``factor``)."""
    return x[..., :2] + factor * x[..., 3:4] * _unit(x[..., 2])


def _attach(parent: int, child: int, x: np.ndarray) -> np.ndarray:
    """Where ``child`` hangs from ``parent`` in state(s) ``x`` of the parent."""
    name = PARTS_2D[child].name
    if parent == 0:
        return _torso_points(x)[_ATTACH[name]]
    return _limb_end(x)


def _grid(n_u: int, n_v: int) -> tuple[np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0.0, 1.0, n_u), np.linspace(-0.5, 0.5, n_v), indexing="ij")
    return u.ravel(), v.ravel()


_GU, _GV = _grid(9, 5)


def _sample_points(i: int, x: np.ndarray, height: np.ndarray | float,
                   width: np.ndarray | float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Points inside part ``i`` for states ``x`` (..., D): (..., K, 2), and each state's area (...).

    ``height`` (the walker's image height) and ``width`` (the part's width as a
    fraction of it, default the model's) broadcast against ``x``'s leading axes.
    """
    part = PARTS_2D[i]
    w = (part.width if width is None else np.asarray(width, float)) * np.asarray(height, float)
    if i == 0:  # the quad of shoulders and hips, widened by half the torso's depth
        t = _torso_points(x)
        half = (0.5 * w)[..., None]
        def widen(a, b):  # noqa: E306 - the segment a-b lengthened by `half` at both ends
            d = b - a
            d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-6)
            return a - half * d, b + half * d
        ls, rs = widen(t["right_shoulder"], t["left_shoulder"])[::-1]
        lh, rh = widen(t["right_hip"], t["left_hip"])[::-1]
        top = rs[..., None, :] + (_GV[:, None] + 0.5) * (ls - rs)[..., None, :]
        bot = rh[..., None, :] + (_GV[:, None] + 0.5) * (lh - rh)[..., None, :]
        pts = bot + _GU[:, None] * (top - bot)
        width = 0.5 * (np.linalg.norm(ls - rs, axis=-1) + np.linalg.norm(lh - rh, axis=-1))
        return pts, x[..., 3] * width
    if part.name == "head":  # a disc of the head's width around the head joint
        centre = _limb_end(x)
        r = np.sqrt(_GU) * 0.5 * w[..., None]
        a = (_GV + 0.5) * 2 * np.pi + _GU * 2.4  # spread the grid over the disc
        pts = centre[..., None, :] + (r[..., None] * _unit(a))
        return pts, np.broadcast_to(np.pi * (0.5 * w) ** 2, x.shape[:-1])
    d = _unit(x[..., 2])
    n = np.stack([d[..., 1], -d[..., 0]], -1)
    length = part.extend * x[..., 3]
    pts = (x[..., None, :2] + (_GU[:, None] * length[..., None, None]) * d[..., None, :]
           + (_GV[:, None] * w[..., None, None]) * n[..., None, :])
    return pts, length * w


def _draw(mask: np.ndarray, i: int, x: np.ndarray, height: float, width: float | None = None) -> None:
    """Draw part ``i`` in state ``x`` (one state) into ``mask`` (value 1), OpenCV capsules
    ``width`` (a fraction of ``height``; default the model's) wide."""
    part = PARTS_2D[i]
    w = max(1, int(round((part.width if width is None else width) * height)))
    s = 16.0  # 4 bits of sub-pixel precision

    def p(v: np.ndarray) -> tuple[int, int]:
        return int(round(v[0] * s)), int(round(v[1] * s))

    if i == 0:
        t = _torso_points(x)
        quad = np.array([t["left_shoulder"], t["right_shoulder"], t["right_hip"], t["left_hip"]])
        cv2.fillConvexPoly(mask, np.round(quad * s).astype(np.int32), 1, cv2.LINE_8, 4)
        cv2.polylines(mask, [np.round(quad * s).astype(np.int32)], True, 1, w, cv2.LINE_8, 4)
    elif part.name == "head":
        cv2.circle(mask, p(_limb_end(x)), int(round(0.5 * w * s)), 1, -1, cv2.LINE_8, 4)
    else:
        cv2.line(mask, p(x[:2]), p(_limb_end(x, part.extend)), 1, w, cv2.LINE_8, 4)


def joints_from_states(states: list[np.ndarray]) -> np.ndarray:
    """The 13 joints (13, 2) of one posture given each part's state."""
    out = np.full((N_JOINTS, 2), np.nan)
    t = _torso_points(states[0])
    for name in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"):
        out[_J[name]] = t[name]
    for i, part in enumerate(PARTS_2D[1:], start=1):
        out[_J[part.distal]] = _limb_end(states[i])
    return out


def part_points(joints: np.ndarray) -> list[tuple[np.ndarray, ...]]:
    """The points that place each part, from 13 joints (2D or 3D): the torso's left and right
    shoulder and hip, a limb's (and the head's) proximal and distal points."""
    j = {name: joints[k] for name, k in _J.items()}
    points = {"neck": 0.5 * (j["left_shoulder"] + j["right_shoulder"]), **j}
    out = [(j["left_shoulder"], j["right_shoulder"], j["left_hip"], j["right_hip"])]
    for part in PARTS_2D[1:]:
        out.append((points[_ATTACH.get(part.name) or _proximal_joint(part)], j[part.distal]))
    return out


def states_from_joints(joints: np.ndarray, height: float) -> list[np.ndarray]:
    """Each part's state from 13 joints (the inverse of :func:`joints_from_states`)."""
    torso, *limbs = part_points(joints)
    return [torso_state(*torso, height)] + [limb_state(*ends, height) for ends in limbs]


def torso_state(ls: np.ndarray, rs: np.ndarray, lh: np.ndarray, rh: np.ndarray, height: float) -> np.ndarray:
    """The torso's state(s) (..., 8) from its shoulders and hips (..., 2): the inverse of
    :func:`_torso_points` (lengths floored at 0.001 of ``height``)."""
    sm, hm = 0.5 * (ls + rs), 0.5 * (lh + rh)
    axis = sm - hm
    ln = np.maximum(np.linalg.norm(axis, axis=-1), 1e-3 * height)
    u = axis / ln[..., None]
    n = np.stack([u[..., 1], -u[..., 0]], -1)
    ds, dh = ls - sm, lh - hm
    dot = lambda a, b: (a * b).sum(-1)  # noqa: E731
    return np.stack([*np.moveaxis(0.5 * (sm + hm), -1, 0), np.arctan2(axis[..., 1], axis[..., 0]), ln,
                     dot(ds, n), dot(ds, u), dot(dh, n), dot(dh, u)], -1)


def limb_state(proximal: np.ndarray, distal: np.ndarray, height: float) -> np.ndarray:
    """A limb's state(s) (..., 4) from its proximal and distal points (..., 2)."""
    d = distal - proximal
    return np.concatenate([proximal, np.arctan2(d[..., 1], d[..., 0])[..., None],
                           np.maximum(np.linalg.norm(d, axis=-1), 1e-3 * height)[..., None]], -1)


def _proximal_joint(part: _Part) -> str:
    return PARTS_2D[_INDEX[part.parent]].distal


# --------------------------------------------------------------------- inference


def _kernel(a: np.ndarray, b: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """Gaussian kernel (B, M, N) between points ``a`` (B, M, k) and ``b`` (B, N, k), widths ``sigma`` (B,)."""
    d2 = (a[:, :, None, 0] - b[:, None, :, 0]) ** 2
    for k in range(1, a.shape[-1]):
        d2 += (a[:, :, None, k] - b[:, None, :, k]) ** 2
    d2 *= (-0.5 / np.asarray(sigma, float) ** 2)[:, None, None]
    return np.exp(d2, out=d2)


class _Beliefs:
    """Particles, weights and the messages each part last received, for a batch of frames.

    ``x[i]`` is part *i*'s particles (B, M, D) for B independent problems
    (one frame in each of B cameras) that share every array operation; each
    has its own random generator, so a problem's draws, and its answer, do
    not depend on the others in its batch.
    """

    def __init__(self, start: list[np.ndarray], height: np.ndarray, config: MNBPConfig,
                 rngs: list[np.random.Generator]) -> None:
        m, b = config.n_particles, len(rngs)
        self.x = [np.repeat(np.asarray(s, float).reshape(b, 1, -1), m, axis=1) for s in start]
        self.w = [np.full((b, m), 1.0 / m) for _ in start]
        self.received = [{k: np.ones((b, m)) for k in _NEIGHBOURS[i]} for i in range(len(start))]
        self.height, self.config, self.rngs = np.asarray(height, float).reshape(b), config, rngs
        self.joint_sigma = config.joint_sigma[0] * self.height  # (B,), annealed with the temperature

    def best(self, i: int) -> np.ndarray:
        """Part ``i``'s heaviest particle in each problem (B, D)."""
        return np.take_along_axis(self.x[i], np.argmax(self.w[i], axis=1)[:, None, None], axis=1)[:, 0]

    @staticmethod
    def attach(parent: int, child: int, x: np.ndarray) -> np.ndarray:
        """Where ``child`` hangs from ``parent`` in the parent's state(s) ``x``."""
        return _attach(parent, child, x)

    @staticmethod
    def proximal(x: np.ndarray) -> np.ndarray:
        """A limb's proximal point in its state(s) ``x``."""
        return x[..., :2]

    def message(self, k: int, i: int, xi: np.ndarray) -> np.ndarray:
        """m_ki at the candidate states ``xi`` (B, M, D) of part ``i`` (eq. 2, particle estimate)."""
        weights = self.w[k] / np.maximum(self.received[k][i], 1e-300)
        weights = weights / weights.sum(axis=1, keepdims=True)
        if PARTS_2D[i].parent is not None and _INDEX[PARTS_2D[i].parent] == k:  # k is i's parent
            kernel = _kernel(self.proximal(xi), self.attach(k, i, self.x[k]), self.joint_sigma)
        else:  # k is i's child
            kernel = _kernel(self.attach(i, k, xi), self.proximal(self.x[k]), self.joint_sigma)
        return np.matmul(kernel, weights[..., None])[..., 0] + 1e-12

    def draws(self, n_uniform: int, n_normal: int) -> tuple[np.ndarray, np.ndarray]:
        """``n_uniform`` uniform and ``n_normal`` standard normal rows of M draws per problem,
        (B, n, M) each, every problem from its own generator (two calls each)."""
        m = self.config.n_particles
        return (np.stack([rng.random((n_uniform, m)) for rng in self.rngs]),
                np.stack([rng.standard_normal((n_normal, m)) for rng in self.rngs]))

    def resample(self, w: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Indices (B, M) drawn from each row of weights ``w`` (B, M) by the uniforms ``u`` (B, M)
        (multinomial resampling: the inverse of each row's cumulative weights)."""
        cdf = np.cumsum(w, axis=1)
        cdf /= cdf[:, -1:]
        idx = np.stack([np.searchsorted(c, v, side="right") for c, v in zip(cdf, u)])
        return np.minimum(idx, w.shape[1] - 1)

    def propose(self, i: int, frac: float) -> np.ndarray:
        """Resample part ``i``'s belief and perturb it (annealed by ``frac`` in [0, 1])."""
        c, h = self.config, self.height
        lerp = lambda a: a[0] + (a[1] - a[0]) * frac  # noqa: E731
        u, z = self.draws(5, 6)
        best = self.best(i)
        x = np.take_along_axis(self.x[i], self.resample(self.w[i], u[:, 0])[..., None], axis=1)
        model = PARTS_2D[i].length * h[:, None]
        x[..., :2] += (lerp(c.step_position) * h)[:, None, None] * z[:, 0:2].transpose(0, 2, 1)
        x[..., 2] += np.deg2rad(lerp(c.step_angle_deg) * z[:, 2])
        length = np.clip(x[..., 3] + (lerp(c.step_length) * model) * z[:, 3],
                         c.length_range[0] * model, c.length_range[1] * model)
        if i == 0:  # the torso moves as a whole: its shape is the start's (see module docstring)
            x[..., 4:8] *= (length / x[..., 3])[..., None]
        x[..., 3] = length
        if i > 0:  # half of a child's particles start at its parent's attachment point
            parent = _INDEX[PARTS_2D[i].parent]
            pick = self.resample(self.w[parent], u[:, 1])
            anchor = _attach(parent, i, np.take_along_axis(self.x[parent], pick[..., None], axis=1))
            half = (u[:, 2] < 0.5)[..., None]
            x[..., :2] = np.where(half, anchor + self.joint_sigma[:, None, None] * z[:, 4:6].transpose(0, 2, 1),
                                  x[..., :2])
            # annealed global moves: a fresh angle within explore_deg of the current best
            wide = u[:, 3] < c.explore * (1.0 - frac)
            turn = (2.0 * u[:, 4] - 1.0) * c.explore_deg
            x[..., 2] = np.where(wide, best[:, None, 2] + np.deg2rad(turn), x[..., 2])
        x[:, 0] = best  # keep the current best
        return x


class SilhouetteView:
    """Silhouettes as mNBP sees them: ``phi_i(x_i, X_-i^(n-1), z)`` (eq. 1-3).

    One or several silhouettes (a batch: one frame's cameras), packed in one
    flat buffer so that every candidate of every silhouette is scored in the
    same array operations; each image has a border of one pixel of ``-1``
    with nothing drawn, onto which every point off the image is clipped.
    Keeps each part's current best drawn (OpenCV capsules) so that part *i*
    is scored against the pixels the other parts leave unexplained: ``G = 0``
    where another part is drawn, ``+1`` on the silhouette, ``-1`` off it. A
    count of the parts drawn on each pixel makes "another part" one
    comparison at the candidates' points, with no image-sized work per call.
    ``widths`` (B, parts) are the parts' widths in each image as fractions of
    its walker's height (default the model's, :data:`PARTS_2D`; the person's
    own from :func:`person_widths`). ``below`` (B,) rows under each image are
    hidden (a wall in front, the frame's bottom edge: :mod:`estimator.occlusion`):
    there, and on the border beside and below them, ``G = 0``, so a shin
    behind the wall is neither pulled up onto the silhouette nor punished.
    """

    def __init__(self, silhouettes: list[np.ndarray], heights: np.ndarray, states: list[np.ndarray],
                 widths: np.ndarray | None = None, below: np.ndarray | None = None) -> None:
        below = np.zeros(len(silhouettes), np.int64) if below is None else np.asarray(below, np.int64)
        self.shapes = np.array([s.shape for s in silhouettes], np.int64).reshape(-1, 2) + np.c_[below, 0 * below]
        padded = self.shapes + 2
        sizes = padded.prod(axis=1)
        self.offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.base = np.concatenate([_observed(s, k).ravel() for s, k in zip(silhouettes, below)])
        self.height = np.asarray(heights, float).reshape(len(silhouettes))
        self.widths = np.broadcast_to(MODEL_WIDTHS if widths is None else np.asarray(widths, float),
                                      (len(silhouettes), len(PARTS_2D)))
        self.drawn = [np.zeros(int(sizes.sum()), np.uint8) for _ in PARTS_2D]
        # pixel (row, col) of image b, -1 <= row <= rows, -1 <= col <= cols, is origin + row * stride + col
        self._rows, self._cols = (self.shapes[:, k, None, None] for k in (0, 1))
        self._stride = self._cols + 2
        self._origin = self.offsets[:, None, None] + self._stride + 1
        for i, x in enumerate(states):
            self._draw(i, x)
        self.count = np.sum(self.drawn, axis=0, dtype=np.uint8)  # parts drawn on each pixel

    def _image(self, flat: np.ndarray, b: int, border: bool = False) -> np.ndarray:
        (h, w), o = self.shapes[b] + 2, self.offsets[b]
        image = flat[o:o + h * w].reshape(h, w)
        return image if border else image[1:-1, 1:-1]

    def _draw(self, i: int, x: np.ndarray) -> None:
        for b in range(len(self.height)):
            _draw(self._image(self.drawn[i], b), i, x[b], self.height[b], self.widths[b, i])

    def log_phi(self, i: int, x: np.ndarray) -> np.ndarray:
        """``log phi_i`` of candidate states ``x`` (B, M, D) of part ``i``, in units of height^2:
        the mean of ``G`` at each candidate's points times its area; off the image ``-1``."""
        pts, area = _sample_points(i, x, self.height[:, None], self.widths[:, i, None])
        ij = np.round(pts).astype(np.int64)
        flat = (self._origin + np.clip(ij[..., 1], -1, self._rows) * self._stride
                + np.clip(ij[..., 0], -1, self._cols))
        g = self.base[flat] * (self.count[flat] <= self.drawn[i][flat])  # X_-i^(n-1) explains the others
        return g.sum(axis=-1) / g.shape[-1] * area / self.height[:, None] ** 2

    def redraw(self, i: int, x: np.ndarray) -> None:
        """Record part ``i``'s new estimate ``x`` (B, D) for the other parts' observations."""
        self.count -= self.drawn[i]
        self.drawn[i][:] = 0
        self._draw(i, x)
        self.count += self.drawn[i]

    def score(self) -> np.ndarray:
        """Per silhouette (B,): sum of ``G`` over the whole drawn body / silhouette area (1 = perfect)."""
        out = np.empty(len(self.height))
        for b in range(len(out)):
            body, g = self._image(self.count, b) > 0, self._image(self.base, b)
            on, off = g > 0, g < 0
            out[b] = (on[body].sum() - off[body].sum() - on[~body].sum()) / max(1, on.sum())
        return out


def _observed(silhouette: np.ndarray, below: int) -> np.ndarray:
    """``G`` of one image with its one-pixel border (:class:`SilhouetteView`): +1 on the silhouette,
    -1 off it and on the border, 0 on ``below`` hidden rows under it and the border around those."""
    g = np.pad(np.where(silhouette > 0, 1, -1).astype(np.int8), ((1, below + 1), (1, 1)), constant_values=-1)
    if below:
        g[-below - 1:] = 0
    return g


def anneal(beliefs: _Beliefs, log_phi, redraw, prior_energy, config: MNBPConfig, scale: np.ndarray | float) -> None:
    """The mNBP iterations (§3): parts root to leaves and back, ``config.n_iterations`` times.

    ``log_phi(i, x)`` scores candidate states (B, M, D) (in units of the
    walker's height squared, summed over the views), ``redraw(i, best)``
    records part *i*'s new estimates (B, D) for the others' observations,
    ``prior_energy(i, x)`` is the unary prior; ``scale`` is the walker's size
    in the states' units, per problem (the articulation width is a fraction
    of it). The temperature and the articulation width decrease
    geometrically (the paper's lambda).
    """
    c = config
    n_parts = len(beliefs.x)
    order = list(range(n_parts)) + list(range(n_parts - 1, -1, -1))
    temps = np.geomspace(c.temperature[0], c.temperature[1], c.n_iterations)
    sigmas = np.geomspace(c.joint_sigma[0], c.joint_sigma[1], c.n_iterations)
    for n, temp in enumerate(temps):
        frac = n / max(1, c.n_iterations - 1)
        beliefs.joint_sigma = sigmas[n] * np.asarray(scale, float) * np.ones(len(beliefs.rngs))
        for i in order:
            x = beliefs.propose(i, frac)
            log_w = log_phi(i, x) / temp - prior_energy(i, x)
            incoming = {k: beliefs.message(k, i, x) for k in _NEIGHBOURS[i]}
            for msg in incoming.values():
                log_w += np.log(msg)
            w = np.exp(log_w - log_w.max(axis=1, keepdims=True))
            beliefs.x[i], beliefs.w[i], beliefs.received[i] = x, w / w.sum(axis=1, keepdims=True), incoming
            redraw(i, beliefs.best(i))


def estimate_postures2d(silhouettes: list[np.ndarray], starts: np.ndarray, *, heights: np.ndarray | None = None,
                        priors: np.ndarray | None = None, seeds: list[int] | None = None,
                        widths: np.ndarray | None = None, below: np.ndarray | None = None,
                        config: MNBPConfig = MNBPConfig()) -> list[Posture2D]:
    """2D postures on several silhouettes at once (one frame's cameras): :func:`estimate_posture2d`
    for each, batched through the same array operations; each answer is the one
    :func:`estimate_posture2d` gives with ``config.seed`` = its seed (default: ``config.seed``).
    ``widths`` (B, parts or parts,): the parts' widths, fractions of each walker's height
    (default the model's). ``below`` (B,): rows of the walker hidden under each silhouette
    (:class:`SilhouetteView`), counted in the default heights."""
    starts = np.asarray(starts, float)
    priors = starts if priors is None else np.asarray(priors, float)
    if heights is None:
        heights = [image_height(s) + (0 if below is None else below[b]) for b, s in enumerate(silhouettes)]
    heights = np.asarray(heights, float)
    seeds = [config.seed] * len(silhouettes) if seeds is None else seeds
    rngs = [np.random.default_rng(s) for s in seeds]

    def batch(joints: np.ndarray) -> list[np.ndarray]:  # per part, the states (B, D)
        per = [states_from_joints(j, h) for j, h in zip(joints, heights)]
        return [np.stack([p[i] for p in per]) for i in range(len(PARTS_2D))]

    beliefs = _Beliefs(batch(starts), heights, config, rngs)
    prior_states = batch(priors)
    view = SilhouetteView(silhouettes, heights, [beliefs.best(i) for i in range(len(PARTS_2D))], widths, below)
    anneal(beliefs, view.log_phi, view.redraw,
           lambda i, x: _prior_energy(i, x, prior_states[i], heights, config), config, heights)
    best = [beliefs.best(i) for i in range(len(PARTS_2D))]
    return [Posture2D(joints_from_states([s[b] for s in best]), float(score), [s[b] for s in best])
            for b, score in enumerate(view.score())]


def estimate_posture2d(silhouette: np.ndarray, start: np.ndarray, *, height: float | None = None,
                       prior: np.ndarray | None = None, config: MNBPConfig = MNBPConfig()) -> Posture2D:
    """The 2D posture on one silhouette by mNBP, started from ``start`` (13, 2).

    Parameters
    ----------
    silhouette : ndarray of shape (H, W), uint8 (non-zero = walker)
    start : ndarray of shape (13, 2)
        Starting joints in the silhouette's pixels (Izo–Grimson's model
        placement, or the previous frame's posture).
    height : float, optional
        The walker's image height in pixels (default: the silhouette's rows).
    prior : ndarray of shape (13, 2), optional
        Centre of the weak unary prior (default: ``start``).
    """
    return estimate_postures2d([silhouette], np.asarray(start, float)[None],
                               heights=None if height is None else [height],
                               priors=None if prior is None else np.asarray(prior, float)[None], config=config)[0]


def image_height(silhouette: np.ndarray) -> float:
    """The walker's height in pixels: the silhouette's rows from first to last (all rows if empty)."""
    rows = np.flatnonzero(silhouette.any(axis=1))
    return float(rows[-1] - rows[0] + 1) if rows.size else float(silhouette.shape[0])


def _prior_energy(i: int, x: np.ndarray, centre: np.ndarray, height: np.ndarray, c: MNBPConfig) -> np.ndarray:
    """Unary prior (B, M): squared distance of the part's points from the starting posture's.

    ``x`` (B, M, D) are candidates, ``centre`` (B, D) the starting states,
    ``height`` (B,). Weak for the limbs (``prior_sigma``), tight for the torso
    (``torso_prior_sigma``): its quad-and-edges outline is too crude for its
    silhouette to place the shoulder and hip centres, which lie inside it
    (measured, ``bench/eval_mnbp.py``: letting it move within 1 % of the
    height made shoulders and hips 0.02-0.03 worse in median error than the
    model placement, 0.6 % better with it held within 0.3 %).

    With ``along_sigma``, a limb's (and the head's) distal end is also held
    at its start's distance from the start's proximal point: a silhouette
    places a limb well across its axis and poorly along it (a tube does not
    show where the knee is), the model's placement the reverse. Measured
    (docs/POSTURE.md, "Along the limbs"): with 0.02, 2D joints 12-14 % and 3D
    postures 6-9 % nearer the truth, but the rig's rotations 0.3-1.0 deg
    worse in median (the prior pulls every view's joints towards the model
    placed at the viewpoints' rig), so it is off by default.
    """
    sigma2 = ((c.torso_prior_sigma if i == 0 else c.prior_sigma) * np.asarray(height, float)[:, None]) ** 2
    centre = centre[:, None]
    if i == 0:
        t, t0 = _torso_points(x), _torso_points(centre)
        d = sum(((t[k] - t0[k]) ** 2).sum(-1) for k in ("left_shoulder", "right_shoulder", "left_hip", "right_hip"))
        return 0.5 * d / 4 / sigma2
    d = ((_limb_end(x) - _limb_end(centre)) ** 2).sum(-1) + ((x[..., :2] - centre[..., :2]) ** 2).sum(-1)
    energy = 0.5 * d / 2 / sigma2
    if c.along_sigma is not None:  # the distal end's distance from the start's proximal point
        along = np.linalg.norm(_limb_end(x) - centre[..., :2], axis=-1) - centre[..., 3]
        energy = energy + 0.5 * (along / (c.along_sigma * np.asarray(height, float)[:, None])) ** 2
    return energy


def posture_sequences(silhouettes: list[list[np.ndarray | None]], boxes: list[np.ndarray], starts: list[np.ndarray],
                      *, config: MNBPConfig = MNBPConfig(), carry: float = 0.5, chain: int | None = 15,
                      seeds: list[int] | None = None, widths: np.ndarray | None = None,
                      hidden: list[np.ndarray | None] | None = None) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """2D postures over several cameras' frames, in full-frame pixels.

    For camera *c*, ``silhouettes[c]`` are crops at ``boxes[c]`` (T, 4: x, y,
    w, h) and ``starts[c]`` (T, 13, 2) the starting joints in the full frame
    (Izo–Grimson's model placement, which also centres each frame's prior).
    Each frame starts from its own start plus ``carry`` x the previous
    frame's correction (its posture minus its start): the previous posture
    carries over relative to the model, which moves with the walker, so the
    walker's travel between frames does not drag it back.

    A camera's frames are cut into chains of about ``chain`` consecutive
    frames (equal lengths; ``None``: one chain) along which the correction
    carries; a chain's first frame starts from its model placement alone.
    Chains and cameras are independent, so one step of every chain is solved
    as one batch (:func:`estimate_postures2d`); camera *c*'s frame *t* draws
    from seed ``seeds[c] + t`` (default ``config.seed + t``), so a frame's
    posture does not depend on the other cameras but through the person's
    widths, measured over all of them.
    ``widths`` (parts,): the person's part widths, fractions of the walker's
    image height; by default the model's, or with ``config.fit_widths``
    measured on these silhouettes at the starts (:func:`person_widths`).
    ``hidden[c]`` (T,): the share of the walker's height hidden below each
    frame's silhouette (:attr:`estimator.pipeline.CameraTrack.hidden`).
    Returns per camera joints (T, 13, 2), NaN where no silhouette, and scores (T,).
    """
    n_cams = len(silhouettes)
    if widths is None and config.fit_widths:
        widths = person_widths(silhouettes, boxes, starts, hidden=hidden)
    seeds = [config.seed] * n_cams if seeds is None else list(seeds)
    starts = [np.asarray(s, float) for s in starts]
    boxes = [np.asarray(b, float) for b in boxes]
    out = [np.full((len(s), N_JOINTS, 2), np.nan) for s in silhouettes]
    scores = [np.full(len(s), np.nan) for s in silhouettes]
    lanes = []  # (camera, its frames in order)
    for c, sils in enumerate(silhouettes):
        n = len(sils)
        for frames in np.array_split(np.arange(n), max(1, -(-n // chain)) if chain else 1):
            if len(frames):
                lanes.append((c, frames))
    correction = np.zeros((len(lanes), N_JOINTS, 2))
    for step in range(max((len(f) for _, f in lanes), default=0)):
        active = []
        for k, (c, frames) in enumerate(lanes):
            t = frames[step] if step < len(frames) else None
            if (t is not None and silhouettes[c][t] is not None and np.all(np.isfinite(starts[c][t]))
                    and np.all(np.isfinite(boxes[c][t]))):
                active.append((k, c, t))
            else:
                correction[k] = 0.0
        if not active:
            continue
        ks = [k for k, _, _ in active]
        origin = np.stack([boxes[c][t, :2] for _, c, t in active])[:, None]
        model = np.stack([starts[c][t] for _, c, t in active])
        below = [_hidden_rows(silhouettes[c][t], hidden, c, t) for _, c, t in active]
        posts = estimate_postures2d([silhouettes[c][t] for _, c, t in active],
                                    model + carry * correction[ks] - origin, priors=model - origin,
                                    seeds=[seeds[c] + t for _, c, t in active], widths=widths, below=below,
                                    config=config)
        for (k, c, t), post, o, m in zip(active, posts, origin, model):
            out[c][t], scores[c][t] = post.joints + o, post.score
            correction[k] = out[c][t] - m
    return out, scores


def _hidden_rows(silhouette: np.ndarray, hidden: list[np.ndarray | None] | None, c: int, t: int) -> int:
    """Rows of the walker hidden under camera *c*'s silhouette of frame *t*, whose lowest
    ``hidden[c][t]`` of the height is hidden (``hidden`` as for :func:`posture_sequences`)."""
    h = image_height(silhouette)
    share = 0.0 if hidden is None or hidden[c] is None else float(hidden[c][t])
    return int(round(whole_height(h, share) - h))


_LIMBS = tuple(i for i, p in enumerate(PARTS_2D) if i > 0 and p.name != "head")
_LIMB_KINDS = [PARTS_2D[i].name.split("_", 1)[1] for i in _LIMBS]  # each limb's kind, left and right alike
_KINDS = tuple(dict.fromkeys(_LIMB_KINDS))  # upper_arm, forearm, thigh, shin
_KIND = np.array([_KINDS.index(k) for k in _LIMB_KINDS])
_ALONG = np.linspace(0.25, 0.75, 7)  # where along a limb its width is read


def person_widths(silhouettes: list[list[np.ndarray | None]], boxes: list[np.ndarray], joints: list[np.ndarray],
                  *, share: float = 0.9, min_samples: int = 40, bounds: tuple[float, float] = (0.6, 1.6),
                  hidden: list[np.ndarray | None] | None = None) -> np.ndarray:
    """The person's part widths (parts,), fractions of the walker's image height, read off the
    silhouettes where the limbs stand free (Wang–Leow §2: a part's size is person-specific).

    For each limb placed by ``joints`` (per camera (T, 13, 2), full frame; the
    crops ``silhouettes`` at ``boxes`` as for :func:`posture_sequences`),
    the silhouette's half-width is its distance transform's ridge across the
    limb's middle half (the largest distance within one model width either
    side of the axis, so an axis a little off the limb still finds it),
    where no other part (at the model's width) lies across it and the ridge
    is not at the end of the search (a limb merged with another). Left and
    right are pooled per kind (upper arm, forearm, thigh, shin), the median
    over every camera and frame, relative to the model's width; a kind with
    fewer than ``min_samples`` readings takes all limbs' median (the body's
    girth), which the torso takes too; the head keeps the model's width.
    Fewer than ``min_samples`` readings in all: the model's widths. The
    capsules are ``share`` of the widths read (a limb's silhouette is widest
    at its middle, where it is read, and mNBP scored on bench/eval_mnbp.py's
    seed 7 placed the joints best at 0.9: median 0.0175 / 0.0179 / 0.0186 at
    1.0, 0.0160 / 0.0168 / 0.0170 at 0.9, 0.0165 / 0.0167 / 0.0169 at 0.8 with
    worse p90s, on the CMU, stylised and model sets). Ratios to the model's
    are held within ``bounds``. ``hidden`` as for :func:`posture_sequences`
    (the heights include what is hidden).
    """
    ratios: list[np.ndarray] = []
    kinds: list[np.ndarray] = []
    for c, (sils, bxs, js) in enumerate(zip(silhouettes, boxes, joints)):
        for t, (sil, box, j) in enumerate(zip(sils, np.asarray(bxs, float), np.asarray(js, float))):
            if sil is None or not sil.any() or not (np.all(np.isfinite(box)) and np.all(np.isfinite(j))):
                continue
            r, k = _width_readings(sil, j - box[:2], _hidden_rows(sil, hidden, c, t))
            ratios.append(r)
            kinds.append(k)
    widths = MODEL_WIDTHS.copy()
    r, k = (np.concatenate(ratios), np.concatenate(kinds)) if ratios else (np.zeros(0), np.zeros(0, int))
    if len(r) < min_samples:
        return widths
    girth = float(np.median(r))
    per_kind = [float(np.median(r[k == n])) if np.sum(k == n) >= min_samples else girth for n in range(len(_KINDS))]
    scale = np.full(len(PARTS_2D), girth)
    scale[_INDEX["head"]] = 1.0  # a head's width does not follow the limbs' (measured: 2D head error 0.0083 -> 0.0099)
    scale[list(_LIMBS)] = np.array(per_kind)[_KIND]
    return widths * np.clip(share * scale, *bounds)


def _width_readings(sil: np.ndarray, joints: np.ndarray, below: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """One silhouette's limb width readings (:func:`person_widths`): ratios to the model's width
    and the limb kind of each (``below``: rows of the walker hidden under it)."""
    height = image_height(sil) + below
    states = states_from_joints(joints, height)
    drawn = np.zeros((len(PARTS_2D), *sil.shape), np.uint8)
    for i, x in enumerate(states):
        _draw(drawn[i], i, x, height)
    count = drawn.sum(axis=0)
    dist = cv2.distanceTransform((sil > 0).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    x = np.stack([states[i] for i in _LIMBS])  # (L, 4)
    w = MODEL_WIDTHS[list(_LIMBS)] * height  # (L,)
    d = _unit(x[:, 2])
    n = np.stack([d[:, 1], -d[:, 0]], -1)
    across = np.arange(-np.ceil(w.max()), np.ceil(w.max()) + 0.25, 0.5)  # half-pixel steps: no ridge pixel missed
    reach = np.abs(across) <= w[:, None]  # (L, across): one model width either side of the axis
    pts = (x[:, None, None, :2] + (_ALONG[:, None, None] * x[:, None, None, 3:4]) * d[:, None, None]
           + across[None, None, :, None] * n[:, None, None])  # (L, along, across, 2)
    ij = np.round(pts).astype(int)
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < sil.shape[1]) & (ij[..., 1] >= 0) & (ij[..., 1] < sil.shape[0])
    inside &= reach[:, None]
    col, row = np.clip(ij[..., 0], 0, sil.shape[1] - 1), np.clip(ij[..., 1], 0, sil.shape[0] - 1)
    ridge = np.where(inside, dist[row, col], 0.0)
    others = np.where(inside, count[row, col] - drawn[np.array(_LIMBS)[:, None, None], row, col], 0) > 0
    peak = np.abs(across[ridge.argmax(axis=-1)])
    free = ~others.any(axis=-1) & (peak < w[:, None] - 0.5) & (ridge.max(axis=-1) > 0)
    # A run of n pixels has its ridge at (n + 1) / 2; a capsule of width w is scored on points
    # spanning w (``_sample_points``), i.e. on runs of w + 1 pixels: w = n - 1 = 2 ridge - 2.
    ratio = (2.0 * ridge.max(axis=-1) - 2.0) / w[:, None]
    return ratio[free], np.broadcast_to(_KIND[:, None], free.shape)[free]


def posture_sequence(silhouettes: list[np.ndarray | None], boxes: np.ndarray, starts: np.ndarray, *,
                     config: MNBPConfig = MNBPConfig(), carry: float = 0.5,
                     chain: int | None = 15) -> tuple[np.ndarray, np.ndarray]:
    """2D postures over one camera's frames, in full-frame pixels (:func:`posture_sequences`
    for one camera). Returns joints (T, 13, 2), NaN where no silhouette, and scores (T,)."""
    joints, scores = posture_sequences([silhouettes], [boxes], [starts], config=config, carry=carry, chain=chain)
    return joints[0], scores[0]


def measure_postures(estimate: WalkEstimate, config: MNBPConfig = MNBPConfig()) -> WalkEstimate:
    """The estimate with each camera's ``joints2d`` measured by mNBP (this stage's entry).

    Runs :func:`posture_sequences` on the silhouettes the estimate was made
    from (``estimate.tracks``, after clean-up), started from its model
    placement, which is kept as ``model_joints2d``; the cameras' frames of
    one instant go through mNBP as one batch. A track without full-frame
    boxes (crops alone) is left as placed, and said in its notes.
    """
    if estimate.tracks is None:
        return estimate
    cameras, measured = {}, []
    for k, (name, cam) in enumerate(estimate.cameras.items()):
        track = estimate.tracks.get(name)
        if track is None or not track.full_frame:
            cameras[name] = replace(cam, notes=cam.notes + ["joints2d: the model's placement (no full-frame boxes)"])
        else:
            measured.append((k, name, cam, track))
    sils, boxes = [tr.silhouettes for *_, tr in measured], [tr.boxes for *_, tr in measured]
    hidden = [tr.hidden for *_, tr in measured]
    starts = [cam.joints2d for _, _, cam, _ in measured]
    widths = person_widths(sils, boxes, starts, hidden=hidden) if config.fit_widths and measured else None
    joints, scores = posture_sequences(sils, boxes, starts, config=config, widths=widths, hidden=hidden,
                                       seeds=[config.seed + 1000 * k for k, *_ in measured])
    for (_, name, cam, _), j, s in zip(measured, joints, scores):
        cameras[name] = replace(cam, joints2d=j, model_joints2d=cam.joints2d, posture_score=s)
    cameras = {name: cameras[name] for name in estimate.cameras}
    notes = ["joints2d measured on each silhouette by mNBP (Wang-Leow §3); model_joints2d: the gait model's placement"]
    if widths is not None:
        ratio = widths / MODEL_WIDTHS
        per_kind = dict(zip(_LIMB_KINDS, ratio[list(_LIMBS)]))  # left and right alike
        notes.append("mNBP limb capsules from the widths measured on the silhouettes: " + ", ".join(
            f"{kind.replace('_', ' ')} x{per_kind[kind]:.2f}" for kind in _KINDS)
            + " of the model's" + (" (too few free limbs: the model's)" if np.all(ratio == 1.0) else ""))
    return replace(estimate, cameras=cameras, notes=estimate.notes + notes)
