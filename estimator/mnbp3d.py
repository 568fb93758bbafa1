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

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .joints import JOINT_INDEX, N_JOINTS
from .pinhole import PinholeCameras, project
from .mnbp import (_ATTACH, _INDEX, PARTS_2D, MNBPConfig, SilhouetteView, _Beliefs, anneal, image_height,
                   limb_state, part_points, torso_state)

__all__ = ["MNBP3DConfig", "Posture3D", "estimate_posture3d", "joints_from_states3d", "part_lengths",
           "posture_sequence3d", "states_from_joints3d"]

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
    """Particles of 3D part states; messages as in 2D (the base class), 3D proposals."""

    def __init__(self, start: list[np.ndarray], stature: float, lengths: np.ndarray, config: MNBP3DConfig,
                 rng: np.random.Generator) -> None:
        super().__init__(start, np.array([stature]), config.mnbp, [rng])
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
        """Resample part ``i``'s belief and perturb it in 3D (annealed by ``frac`` in [0, 1]).

        One problem (a batch of one: the frame's 3D posture), shape (1, M, D)."""
        c, m, h, rng = self.config, self.config.n_particles, self.height[0], self.rngs[0]
        lerp = lambda a: a[0] + (a[1] - a[0]) * frac  # noqa: E731
        x = self.x[i][0][rng.choice(m, size=m, p=self.w[i][0])]
        if i == 0:  # rigid: a small rotation about the centroid and a shift
            pts = x.reshape(m, 4, 3)
            centroid = pts.mean(axis=1, keepdims=True)
            turn = Rotation.from_rotvec(rng.normal(0.0, 0.5 * np.deg2rad(lerp(c.step_angle_deg)), (m, 3))).as_matrix()
            pts = centroid + np.einsum("mab,mkb->mka", turn, pts - centroid)
            pts += rng.normal(0.0, lerp(c.step_position) * h, (m, 1, 3))
            x = pts.reshape(m, 12)
        else:
            prox = x[:, :3] + rng.normal(0.0, lerp(c.step_position) * h, (m, 3))
            d = x[:, 3:] - x[:, :3]
            length = np.linalg.norm(d, axis=1)
            u = d / np.maximum(length, 1e-9)[:, None] + rng.normal(0.0, np.deg2rad(lerp(c.step_angle_deg)), (m, 3))
            own, tol = self.lengths[i], self.config3d.length_tolerance
            length = np.clip(length + rng.normal(0.0, lerp(c.step_length) * own, m), (1 - tol) * own, (1 + tol) * own)
            parent = _INDEX[PARTS_2D[i].parent]
            half = rng.random(m) < 0.5  # half of a child's particles start at its parent's attachment point
            pick = rng.choice(m, size=int(half.sum()), p=self.w[parent][0])
            prox[half] = self.attach(parent, i, self.x[parent][0][pick]) + rng.normal(
                0.0, self.joint_sigma[0], (int(half.sum()), 3))
            wide = rng.random(m) < c.explore * (1.0 - frac)  # annealed global moves about the best direction
            if wide.any():
                best = self.best(i)[0]
                b = (best[3:] - best[:3]) / max(float(np.linalg.norm(best[3:] - best[:3])), 1e-9)
                axis = np.cross(b, rng.normal(size=(int(wide.sum()), 3)))
                axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-9)
                angle = np.deg2rad(rng.uniform(-1, 1, int(wide.sum())) * c.explore_deg)
                u[wide] = Rotation.from_rotvec(axis * angle[:, None]).apply(b)
            u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-9)
            x = np.concatenate([prox, prox + u * length[:, None]], axis=1)
        x[0] = self.best(i)[0]  # keep the current best
        return x[None]


def _to_view(i: int, x: np.ndarray, camera: PinholeCameras, origin: np.ndarray, height: float) -> np.ndarray:
    """3D states ``x`` (M, D) of part ``i`` as 2D states in one ``camera``'s crop at ``origin``."""
    p = project(camera, x.reshape(len(x), -1, 3))[0] - origin
    if i == 0:
        return torso_state(p[:, 0], p[:, 1], p[:, 2], p[:, 3], height)
    return limb_state(p[:, 0], p[:, 1], height)


def _prior_energy3d(i: int, x: np.ndarray, centre: np.ndarray, stature: float, config: MNBP3DConfig) -> np.ndarray:
    """Unary prior (..., M) of candidates ``x`` (..., M, D): mean squared distance of the part's
    points from the start's ``centre`` (D,), over 2 sigma^2."""
    sigma = (config.mnbp.torso_prior_sigma if i == 0 else config.mnbp.prior_sigma) * stature
    d = ((x - centre).reshape(*x.shape[:-1], -1, 3) ** 2).sum(-1).mean(-1)
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


def estimate_posture3d(silhouettes: list[np.ndarray | None], origins: np.ndarray, cameras: PinholeCameras,
                       start: np.ndarray, *, stature: float, lengths: np.ndarray,
                       config: MNBP3DConfig = MNBP3DConfig(), seed: int = 0) -> Posture3D:
    """The 3D posture of one frame from every view's silhouette, started from ``start`` (13, 3).

    Parameters
    ----------
    silhouettes : list of (H, W) uint8 or None
        One crop per camera (None: that camera did not see the walker).
    origins : ndarray of shape (C, 2)
        Each crop's top-left corner in the full frame (the cameras' pixels).
    cameras : PinholeCameras
    start : ndarray of shape (13, 3)
        Starting joints (round one's), in the cameras' world units; also the prior's centre.
    stature : float
        The walker's stature in those units.
    lengths : ndarray of shape (P,)
        Each part's own length (:func:`part_lengths`).
    """
    rng = np.random.default_rng(seed)
    start_states = states_from_joints3d(np.asarray(start, float))
    beliefs = _Beliefs3D(start_states, stature, lengths, config, rng)
    seen = [c for c, sil in enumerate(silhouettes) if sil is not None and sil.any()]
    if not seen:
        return Posture3D(np.asarray(start, float).copy(), float("nan"))
    views = [(cameras.select(c), origins[c], image_height(silhouettes[c])) for c in seen]

    def to_views(i: int, x: np.ndarray) -> np.ndarray:  # 3D states (M, D) -> 2D states in every view (C, M, D2)
        return np.stack([_to_view(i, x, cam, o, h) for cam, o, h in views])

    view = SilhouetteView([silhouettes[c] for c in seen], [h for *_, h in views],
                          [to_views(i, s[None])[:, 0] for i, s in enumerate(start_states)])
    anneal(beliefs, lambda i, x: view.log_phi(i, to_views(i, x[0])).sum(axis=0, keepdims=True),
           lambda i, best: view.redraw(i, to_views(i, best)[:, 0]),
           lambda i, x: _prior_energy3d(i, x, start_states[i], stature, config), config.mnbp, stature)
    joints = joints_from_states3d([beliefs.best(i)[0] for i in range(len(PARTS_2D))])
    return Posture3D(joints, float(np.mean(view.score())))


def posture_sequence3d(silhouettes: list[list[np.ndarray | None]], boxes: np.ndarray, cameras: PinholeCameras,
                       starts: np.ndarray, *, stature: float, config: MNBP3DConfig = MNBP3DConfig(),
                       seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """3D postures (T, 13, 3) and scores (T,) of a segment: :func:`estimate_posture3d` per frame.

    ``silhouettes[c][t]`` are crops at ``boxes[c, t]`` (x, y, w, h, full frame),
    ``starts`` (T, 13, 3) round one's joints; a frame whose start is not
    finite, or that no camera saw, keeps its start (NaN stays NaN).
    """
    starts = np.asarray(starts, float)
    lengths = part_lengths(starts)
    out, scores = starts.copy(), np.full(len(starts), np.nan)
    for t in range(len(starts)):
        if not np.all(np.isfinite(starts[t])):
            continue
        sils = [s[t] if np.all(np.isfinite(boxes[c, t])) else None for c, s in enumerate(silhouettes)]
        post = estimate_posture3d(sils, boxes[:, t, :2], cameras, starts[t], stature=stature, lengths=lengths,
                                  config=config, seed=seed + t)
        out[t], scores[t] = post.joints, post.score
    return out, scores
