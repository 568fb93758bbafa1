"""3D posture over all calibrated views by mNBP: the second round of Wang–Leow's loop (§3, §5).

Round one measures a 2D posture on each silhouette alone (:mod:`estimator.mnbp`)
and self-calibrates the rig from them (:mod:`estimator.rig`). "In the next
iteration, the reconstructed camera relative motion can be used to help
estimate both 2D and 3D positions of body joints, by combining the image
information coming from the two camera views" (§5): here each body part's
pose is a 3D state, its candidates are projected through every calibrated
(pinhole) camera and scored on every silhouette at once, with the other
parts' previous estimates drawn in each view (the occlusion-aware
observation of eq. 1-3, :class:`estimator.mnbp.SilhouetteView`). An arm
hidden behind the torso in one view is placed by the view that sees it, and
the left/right ambiguity of one silhouette is settled by the others.

Parts are those of the 2D graph (:data:`estimator.mnbp.PARTS_2D`). A limb's
(and the head's) state is its proximal and distal 3D points; its length is
held near the person's own (round one's median over the frames,
``length_tolerance``), which makes the per-part scale of 2D mNBP unneeded:
the projection gives each view its size. The torso's state is its two
shoulders and two hips; it moves as a rigid body (translation and rotation
about its centroid) with round one's shape. Beliefs, messages (eq. 2),
annealing and the prior around the start are those of the 2D round
(:func:`estimator.mnbp.anneal`); the articulation potential is a Gaussian
on the 3D gap between a child's proximal point and its parent's attachment
point, its width a fraction of the stature.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from .joints import JOINT_INDEX, N_JOINTS
from .pinhole import PinholeCameras, project
from .mnbp import (_ATTACH, _INDEX, PARTS_2D, MNBPConfig, SilhouetteView, _Beliefs, _hidden_rows, anneal,
                   image_height, limb_state, part_points, torso_state)

__all__ = ["MNBP3DConfig", "Posture3D", "estimate_posture3d", "joints_from_states3d", "part_lengths",
           "posture_sequence3d", "postures3d", "states_from_joints3d"]

_J = JOINT_INDEX
_TORSO = ("left_shoulder", "right_shoulder", "left_hip", "right_hip")


@dataclass(frozen=True)
class MNBP3DConfig:
    """Settings of the 3D round; lengths are fractions of the stature.

    ``mnbp`` holds the shared settings (particles, iterations, annealing,
    steps); the 3D round starts near its answer (round one's 3D joints), so
    it runs fewer iterations with smaller first steps than the 2D round. The
    torso is held as in the 2D round (``mnbp.torso_prior_sigma``, 0.003 of the
    stature): at the truth with true cameras a free torso (0.02) drifted 0.03
    of the stature, a held one 0.01.
    """

    mnbp: MNBPConfig = MNBPConfig(n_iterations=4, joint_sigma=(0.04, 0.012), step_position=(0.015, 0.004),
                                  step_angle_deg=(12.0, 3.0), step_length=(0.05, 0.02), explore=0.25,
                                  explore_deg=45.0, prior_sigma=0.1)
    length_tolerance: float = 0.15  # a limb's length within this of the person's own


@dataclass
class Posture3D:
    """The 3D posture of one frame: 13 joints and the mean silhouette score over the views."""

    joints: np.ndarray  # (13, 3)
    score: float


def states_from_joints3d(joints: np.ndarray) -> list[np.ndarray]:
    """Each part's 3D state from 13 joints (13, 3): the torso's four points, a limb's two."""
    return [np.concatenate(points) for points in part_points(joints)]


def joints_from_states3d(states: list[np.ndarray]) -> np.ndarray:
    """The 13 joints (13, 3) of 3D part states (the inverse of :func:`states_from_joints3d`)."""
    out = np.full((N_JOINTS, 3), np.nan)
    for k, name in enumerate(_TORSO):
        out[_J[name]] = states[0][3 * k:3 * k + 3]
    for i, part in enumerate(PARTS_2D[1:], start=1):
        out[_J[part.distal]] = states[i][3:6]
    return out


class _Beliefs3D(_Beliefs):
    """Particles of 3D part states for a batch of frames; messages as in 2D (the base class),
    3D proposals."""

    def __init__(self, start: list[np.ndarray], stature: float, lengths: np.ndarray, config: MNBP3DConfig,
                 rngs: list[np.random.Generator]) -> None:
        super().__init__(start, np.full(len(rngs), stature), config.mnbp, rngs)
        self.lengths, self.config3d = lengths, config

    @staticmethod
    def attach(parent: int, child: int, x: np.ndarray) -> np.ndarray:
        if parent != 0:
            return x[..., 3:6]
        name = _ATTACH[PARTS_2D[child].name]
        if name == "neck":
            return 0.5 * (x[..., 0:3] + x[..., 3:6])
        k = _TORSO.index(name)
        return x[..., 3 * k:3 * k + 3]

    @staticmethod
    def proximal(x: np.ndarray) -> np.ndarray:
        return x[..., :3]

    def propose(self, i: int, frac: float) -> np.ndarray:
        """Resample part ``i``'s belief and perturb it in 3D (annealed by ``frac`` in [0, 1])."""
        c, h = self.config, self.height[:, None, None]
        lerp = lambda a: a[0] + (a[1] - a[0]) * frac  # noqa: E731
        u, z = self.draws(5, 13)
        b, m = u.shape[0], u.shape[2]
        normal = lambda k: z[:, k:k + 3].transpose(0, 2, 1)  # noqa: E731 - three rows as (B, M, 3)
        best = self.best(i)
        x = np.take_along_axis(self.x[i], self.resample(self.w[i], u[:, 0])[..., None], axis=1)
        if i == 0:  # rigid: a small rotation about the centroid and a shift
            pts = x.reshape(b, m, 4, 3)
            centroid = pts.mean(axis=2, keepdims=True)
            turn = Rotation.from_rotvec((0.5 * np.deg2rad(lerp(c.step_angle_deg)) * normal(0)).reshape(-1, 3))
            pts = centroid + np.einsum("nab,nkb->nka", turn.as_matrix(), (pts - centroid).reshape(-1, 4, 3)
                                       ).reshape(b, m, 4, 3)
            pts = pts + (lerp(c.step_position) * h * normal(3))[:, :, None]
            x = pts.reshape(b, m, 12)
        else:
            prox = x[..., :3] + lerp(c.step_position) * h * normal(0)
            d = x[..., 3:] - x[..., :3]
            length = np.linalg.norm(d, axis=-1)
            direction = d / np.maximum(length, 1e-9)[..., None] + np.deg2rad(lerp(c.step_angle_deg)) * normal(3)
            own, tol = self.lengths[i], self.config3d.length_tolerance
            length = np.clip(length + lerp(c.step_length) * own * z[:, 6], (1 - tol) * own, (1 + tol) * own)
            parent = _INDEX[PARTS_2D[i].parent]
            # half of a child's particles start at its parent's attachment point
            anchor = self.attach(parent, i, np.take_along_axis(self.x[parent], self.resample(
                self.w[parent], u[:, 1])[..., None], axis=1)) + self.joint_sigma[:, None, None] * normal(7)
            prox = np.where((u[:, 2] < 0.5)[..., None], anchor, prox)
            # annealed global moves: a direction turned about a random axis square to the best's
            axis0 = best[:, 3:] - best[:, :3]
            axis0 = axis0 / np.maximum(np.linalg.norm(axis0, axis=-1, keepdims=True), 1e-9)
            spin = np.cross(axis0[:, None], normal(10))
            spin /= np.maximum(np.linalg.norm(spin, axis=-1, keepdims=True), 1e-9)
            angle = np.deg2rad((2.0 * u[:, 4] - 1.0) * c.explore_deg)
            turned = Rotation.from_rotvec((spin * angle[..., None]).reshape(-1, 3)).apply(
                np.repeat(axis0, m, axis=0)).reshape(b, m, 3)
            direction = np.where((u[:, 3] < c.explore * (1.0 - frac))[..., None], turned, direction)
            direction /= np.maximum(np.linalg.norm(direction, axis=-1, keepdims=True), 1e-9)
            x = np.concatenate([prox, prox + direction * length[..., None]], axis=-1)
        x[:, 0] = best  # keep the current best
        return x


def _prior_energy3d(i: int, x: np.ndarray, centre: np.ndarray, stature: float, config: MNBP3DConfig) -> np.ndarray:
    """Unary prior (B, M) of candidates ``x`` (B, M, D): mean squared distance of the part's
    points from each frame's start ``centre`` (B, D), over 2 sigma^2."""
    sigma = (config.mnbp.torso_prior_sigma if i == 0 else config.mnbp.prior_sigma) * stature
    d = ((x - centre[:, None]).reshape(*x.shape[:-1], -1, 3) ** 2).sum(-1).mean(-1)
    return 0.5 * d / sigma ** 2


def part_lengths(joints3d: np.ndarray) -> np.ndarray:
    """Each part's median 3D length over frames (P,), from joints (T, 13, 3); the torso's is 0."""
    states = [states_from_joints3d(j) for j in np.asarray(joints3d, float) if np.all(np.isfinite(j))]
    if not states:
        raise ValueError("no frame with all 13 joints")
    out = np.zeros(len(PARTS_2D))
    for i in range(1, len(PARTS_2D)):
        s = np.array([st[i] for st in states])
        out[i] = float(np.median(np.linalg.norm(s[:, 3:] - s[:, :3], axis=1)))
    return out


def postures3d(silhouettes: list[list[np.ndarray | None]], origins: np.ndarray, cameras: PinholeCameras,
               starts: np.ndarray, *, stature: float, lengths: np.ndarray, config: MNBP3DConfig = MNBP3DConfig(),
               seeds: list[int], widths: np.ndarray | None = None,
               below: np.ndarray | None = None) -> list[Posture3D]:
    """3D postures of several frames at once, each from every view's silhouette (one batch).

    Parameters
    ----------
    silhouettes : list over frames of lists over cameras of (H, W) uint8 or None
        Each frame's crop per camera (None: that camera did not see the walker).
    origins : ndarray of shape (B, C, 2)
        Each crop's top-left corner in the full frame (the cameras' pixels).
    cameras : PinholeCameras
    starts : ndarray of shape (B, 13, 3)
        Starting joints (round one's), in the cameras' world units; also the prior's centres.
    stature : float
        The walker's stature in those units.
    lengths : ndarray of shape (P,)
        Each part's own length (:func:`part_lengths`).
    seeds : list of int
        One per frame: a frame's answer depends on its seed alone, not on the batch.
    widths : ndarray of shape (P,), optional
        The parts' widths as fractions of the walker's image height, the same in
        every view (the person's, :func:`estimator.mnbp.person_widths`); the
        model's by default.
    below : list over frames of lists over cameras of int, optional
        Rows of the walker hidden under each crop (a wall in front, the image's
        bottom edge): neither walker nor background there
        (:class:`estimator.mnbp.SilhouetteView`).
    """
    starts = np.asarray(starts, float)
    views = [(b, c) for b, sils in enumerate(silhouettes) for c, sil in enumerate(sils)
             if sil is not None and sil.any()]
    posed = sorted({b for b, _ in views})
    out = [Posture3D(s.copy(), float("nan")) for s in starts]
    if not posed:
        return out
    slot = {b: k for k, b in enumerate(posed)}  # the frames with a view, as the batch's problems
    vb = np.array([slot[b] for b, _ in views])
    vc = np.array([c for _, c in views])
    origin = np.asarray(origins, float)[[b for b, _ in views], vc][:, None]  # (V, 1, 2)
    hid = np.array([0 if below is None else below[b][c] for b, c in views], np.int64)  # per view
    heights = np.array([image_height(silhouettes[b][c]) for b, c in views]) + hid
    first = np.flatnonzero(np.r_[True, vb[1:] != vb[:-1]])  # each problem's first view (views are by frame)
    per = [states_from_joints3d(starts[b]) for b in posed]
    start_states = [np.stack([p[i] for p in per]) for i in range(len(PARTS_2D))]

    def to_views(i: int, x: np.ndarray) -> np.ndarray:
        """3D states (B, M, D) -> 2D states (V, M, D2) in every view of their frame."""
        p = project(cameras, x.reshape(*x.shape[:2], -1, 3))[vc, vb] - origin[:, None]
        if i == 0:
            return torso_state(p[..., 0, :], p[..., 1, :], p[..., 2, :], p[..., 3, :], heights[:, None])
        return limb_state(p[..., 0, :], p[..., 1, :], heights[:, None])

    beliefs = _Beliefs3D(start_states, stature, lengths, config, [np.random.default_rng(seeds[b]) for b in posed])
    view = SilhouetteView([silhouettes[b][c] for b, c in views], heights,
                          [to_views(i, s[:, None])[:, 0] for i, s in enumerate(start_states)], widths, hid)
    anneal(beliefs, lambda i, x: np.add.reduceat(view.log_phi(i, to_views(i, x)), first, axis=0),
           lambda i, best: view.redraw(i, to_views(i, best[:, None])[:, 0]),
           lambda i, x: _prior_energy3d(i, x, start_states[i], stature, config), config.mnbp, stature)
    best = [beliefs.best(i) for i in range(len(PARTS_2D))]
    scores = np.add.reduceat(view.score(), first) / np.diff(np.r_[first, len(views)])
    for k, b in enumerate(posed):
        out[b] = Posture3D(joints_from_states3d([s[k] for s in best]), float(scores[k]))
    return out


def estimate_posture3d(silhouettes: list[np.ndarray | None], origins: np.ndarray, cameras: PinholeCameras,
                       start: np.ndarray, *, stature: float, lengths: np.ndarray,
                       config: MNBP3DConfig = MNBP3DConfig(), seed: int = 0) -> Posture3D:
    """The 3D posture of one frame from every view's silhouette, started from ``start`` (13, 3)
    (:func:`postures3d` for one frame; ``origins`` (C, 2))."""
    return postures3d([silhouettes], np.asarray(origins, float)[None], cameras, np.asarray(start, float)[None],
                      stature=stature, lengths=lengths, config=config, seeds=[seed])[0]


def posture_sequence3d(silhouettes: list[list[np.ndarray | None]], boxes: np.ndarray, cameras: PinholeCameras,
                       starts: np.ndarray, *, stature: float, config: MNBP3DConfig = MNBP3DConfig(),
                       seed: int = 0, widths: np.ndarray | None = None,
                       hidden: list[np.ndarray | None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """3D postures (T, 13, 3) and scores (T,) of a segment, its frames solved as one batch
    (:func:`postures3d`, frame *t* with seed ``seed + t``, the parts ``widths`` wide).

    ``silhouettes[c][t]`` are crops at ``boxes[c, t]`` (x, y, w, h, full frame),
    ``starts`` (T, 13, 3) round one's joints; a frame whose start is not
    finite, or that no camera saw, keeps its start (NaN stays NaN).
    ``hidden[c]`` (T,): the share of the walker's height hidden below each
    of camera *c*'s crops (:attr:`estimator.pipeline.CameraTrack.hidden`).
    """
    starts = np.asarray(starts, float)
    lengths = part_lengths(starts)
    out, scores = starts.copy(), np.full(len(starts), np.nan)
    frames = [t for t in range(len(starts)) if np.all(np.isfinite(starts[t]))]
    if not frames:
        return out, scores
    sils = [[s[t] if np.all(np.isfinite(boxes[c, t])) else None for c, s in enumerate(silhouettes)] for t in frames]
    below = [[0 if s is None else _hidden_rows(s, hidden, c, t)
              for c, s in enumerate(row)] for t, row in zip(frames, sils)]
    posts = postures3d(sils, np.moveaxis(boxes[:, frames, :2], 0, 1), cameras, starts[frames], stature=stature,
                       lengths=lengths, config=config, seeds=[seed + t for t in frames], widths=widths, below=below)
    for t, post in zip(frames, posts):
        out[t], scores[t] = post.joints, post.score
    return out, scores
