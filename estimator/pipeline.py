"""Walking pose and camera viewpoints from multi-view silhouettes (Izo–Grimson §3).

The online path for one window of synchronized frames:

1. register every silhouette and match it to the appearance clusters (§3
   step 3, eq. 8);
2. per camera, fit the viewpoint ellipse to a cloud of example viewpoints,
   settling ahead/behind by the walker's motion in the full frame (§3 step 4,
   :mod:`estimator.viewpoint`). The paper's cloud is every member of the matched
   clusters; with exemplars (:mod:`estimator.exemplars`) each member of the
   ``top_clusters`` best clusters is weighted by ``exp(-d / tau)``, d its own
   eq. 8 distance to the input, which sharpens the cloud;
3. per frame and camera, evidence about the phase. The paper: the circular mean
   phase of the matched cluster's members, fed to the HMM through the eq. 9
   mixture. With exemplars: the eq. 8 distance of the input to the examples of
   every phase seen from the camera's estimated viewpoint, used directly as the
   HMM's log-emission ``-d / tau_phase`` (summed over cameras);
4. the cyclic HMM's Viterbi path (§6, :mod:`estimator.hmm`);
5. on the paper's path only: the equal-weight eq. 9 cannot tell a phase from
   its opposite (left from right), so the path and its half-cycle shift are
   scored by the distances to the clusters holding the examples at (phase,
   estimated viewpoint), and the better one is kept;
6. 3D joints of the model body at the decoded phase (person frame) and, per
   camera, their projection placed on the observed silhouette's box.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .appearance import AppearanceModel
from .body import PARTS
from .cleanup import CleanupConfig, CleanupReport, isolate_walker, trim_below_feet
from .camera import world_to_camera_rotation
from .exemplars import ExemplarIndex, hamming, pack
from .gait import GaitModel, load_gait
from .hmm import PhaseHMM, viterbi
from .joints import JOINT_NAMES, N_JOINTS
from .registration import distance
from .sequence import Sequence
from .skeleton import FULL_JOINT_NAMES, BodyShape, forward_kinematics
from .viewpoint import MotionCue, Viewpoint, azimuth_difference_deg, estimate_viewpoint, motion_cue

__all__ = ["CameraTrack", "EstimateConfig", "clean_tracks", "WalkEstimate", "estimate_walk", "track_length", "tracks_from_sequence"]

_J = {name: i for i, name in enumerate(FULL_JOINT_NAMES)}


@dataclass(frozen=True)
class EstimateConfig:
    """Options of :func:`estimate_walk`; defaults are what the evaluation measured.

    Parameters
    ----------
    method : {"exemplars", "paper"}
        ``"paper"`` uses the cluster means only (§3 steps 3-5 as published);
        ``"exemplars"`` also compares inputs with the clusters' members.
    hmm : PhaseHMM
        The phase model (§6): transitions, and eq. 9 on the paper's path.
    top_clusters : int
        Clusters per frame whose members enter the viewpoint cloud (exemplar path).
    tau_view : float
        Temperature, in pixels of the registered canvas, of the members' weights.
    tau_phase : float
        Temperature of the phase log-emission (pixels).
    phase_view_window_deg : float
        Paper's path: members within this angle of the camera's estimated
        viewpoint give the phase observation; ``inf`` uses all (the paper).
    resolve_half_cycle : bool
        Paper's path: score the Viterbi path against its half-cycle shift (step 5).
    body : BodyShape
        The model body whose joints are reported.
    cleanup : CleanupConfig or None
        Reduce each silhouette to the walker first (:mod:`estimator.cleanup`);
        None feeds the silhouettes to registration as they are.
    """

    method: str = "exemplars"
    hmm: PhaseHMM = field(default_factory=PhaseHMM)
    top_clusters: int = 3
    tau_view: float = 3.0
    tau_phase: float = 30.0
    phase_view_window_deg: float = 30.0
    resolve_half_cycle: bool = True
    body: BodyShape = field(default_factory=BodyShape)
    cleanup: CleanupConfig | None = field(default_factory=CleanupConfig)

    def __post_init__(self) -> None:
        if self.method not in ("exemplars", "paper"):
            raise ValueError(f"method must be 'exemplars' or 'paper', got {self.method!r}")


@dataclass
class CameraTrack:
    """One camera's silhouettes over a window.

    Attributes
    ----------
    silhouettes : list of (ndarray of shape (h, w), uint8, or None)
        Per frame: the silhouette crop, or None when the camera has no data.
    boxes : ndarray of shape (T, 4)
        ``(x, y, width, height)`` of each crop in the full frame; NaN rows where
        unknown. With ``full_frame`` False the boxes are only the crops' own
        extents and carry no motion.
    full_frame : bool
        Whether the boxes are positions in the camera's full frame.
    image_size : (int, int), optional
        ``(width, height)`` of the full frame, when known: a walker touching
        its border is cut by it (:mod:`estimator.cleanup`).
    """

    silhouettes: list[np.ndarray | None]
    boxes: np.ndarray
    full_frame: bool = True
    image_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        self.boxes = np.asarray(self.boxes, dtype=float)
        if self.boxes.shape != (len(self.silhouettes), 4):
            raise ValueError(f"boxes must have shape ({len(self.silhouettes)}, 4), got {self.boxes.shape}")


def crop_to_box(silhouette: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """The tight crop of a binary silhouette and its box ``(x, y, w, h)``; None if empty."""
    rows = np.flatnonzero(silhouette.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(silhouette.any(axis=0))
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    return silhouette[y0:y1, x0:x1], np.array([x0, y0, x1 - x0, y1 - y0], float)


def tracks_from_sequence(sequence: Sequence) -> dict[str, CameraTrack]:
    """Camera tracks from a sequence folder's silhouettes.

    Full-frame silhouettes (the rig's image size) are cropped to their box and
    keep their position; smaller PNGs are crops whose position is unknown.
    """
    tracks = {}
    for cam in sequence.cameras:
        sils, boxes, full = [], [], []
        for s in sequence.silhouettes[cam]:
            if s is None:
                sils.append(None)
                boxes.append([np.nan] * 4)
                continue
            is_full = (s.shape[1], s.shape[0]) == tuple(sequence.image_size)
            cropped = crop_to_box(s)
            if cropped is None:
                sils.append(None)
                boxes.append([np.nan] * 4)
                continue
            sils.append(cropped[0])
            boxes.append(cropped[1])  # in the full frame, or in the crop's own pixels
            full.append(is_full)
        full_frame = bool(full) and all(full)
        tracks[cam] = CameraTrack(sils, np.array(boxes, float).reshape(-1, 4), full_frame=full_frame,
                                  image_size=tuple(sequence.image_size) if full_frame else None)
    return tracks


@dataclass
class CameraEstimate:
    """Per-camera results."""

    viewpoint: Viewpoint
    cue: MotionCue | None
    labels: np.ndarray  # (T,), -1 where no silhouette
    observations: np.ndarray  # (T,) phase observation, NaN where none
    joints2d: np.ndarray  # (T, 13, 2), NaN where no silhouette
    notes: list[str]
    cleanup: CleanupReport | None = None


@dataclass
class WalkEstimate:
    """Estimated walk over a window: per-frame phase and joints, per-camera viewpoint."""

    phase: np.ndarray  # (T,)
    states: np.ndarray  # (T,) HMM states
    joints3d: np.ndarray  # (T, 13, 3) person frame
    cameras: dict[str, CameraEstimate]
    log_prob: float
    half_cycle_margin: float
    notes: list[str] = field(default_factory=list)
    tracks: dict[str, CameraTrack] | None = None  # the tracks estimated from (after clean-up)

    def to_result(self, *, first_index: int = 0) -> dict:
        """The result format of DESIGN.md (JSON-able)."""
        cams = {}
        for name, c in self.cameras.items():
            d = c.viewpoint.to_dict()
            d["motion_cue"] = None if c.cue is None else {"growth_per_frame": round(c.cue.growth, 5), "travel_heights_per_frame": round(c.cue.travel, 5)}
            d["notes"] = c.notes
            cams[name] = d
        frames = []
        for t in range(len(self.phase)):
            j2d = {
                name: np.round(c.joints2d[t], 2).tolist()
                for name, c in self.cameras.items()
                if np.all(np.isfinite(c.joints2d[t]))
            }
            frames.append({
                "index": first_index + t,
                "phase": round(float(self.phase[t]), 4),
                "joints3d": np.round(self.joints3d[t], 4).tolist(),
                "joints2d": j2d,
                "observed_phase": {
                    name: (None if np.isnan(c.observations[t]) else round(float(c.observations[t]), 4))
                    for name, c in self.cameras.items()
                },
            })
        return {
            "joint_names": list(JOINT_NAMES),
            "cameras": cams,
            "frames": frames,
            "hmm": {
                "log_prob": self.log_prob if np.isfinite(self.log_prob) else None,
                "half_cycle_margin": round(self.half_cycle_margin, 4) if np.isfinite(self.half_cycle_margin) else None,
            },
            "notes": self.notes,
        }


def _abs_az_diff(a: np.ndarray, b: float) -> np.ndarray:
    return np.abs(azimuth_difference_deg(a, b))


def _circular_mean(values: np.ndarray) -> float:
    ang = 2 * np.pi * values
    return float((np.arctan2(np.sin(ang).sum(), np.cos(ang).sum()) / (2 * np.pi)) % 1.0)


def _example_lookup(model: AppearanceModel, n_phases: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cluster of the example at each (phase, azimuth, elevation) grid point, -1 where none.

    With several bodies on the grid (taking turns or not) any member at a grid
    point stands for it.
    """
    labels = np.repeat(np.arange(model.n_clusters), np.diff(model.member_offsets))
    az = np.unique(model.member_azimuth_deg)
    el = np.unique(model.member_elevation_deg)
    table = np.full((n_phases, len(az), len(el)), -1, np.int64)
    pi = np.round(model.member_phase * n_phases).astype(int) % n_phases
    table[pi, np.searchsorted(az, model.member_azimuth_deg), np.searchsorted(el, model.member_elevation_deg)] = labels
    return table, az, el


def _place_joints(person: np.ndarray, body: BodyShape, vp: Viewpoint, boxes: np.ndarray) -> np.ndarray:
    """Project the model's joints with the viewpoint and fit them to each box.

    ``person`` holds all skeleton joints (T, 20, 3). Vertical: the body from the
    top of the head to the bottom of the feet spans the box height; horizontal:
    the body's extent is centred on the box. Returns (T, 13, 2).
    """
    R = world_to_camera_rotation(vp.azimuth_deg, vp.elevation_deg)
    uv = person @ R[:2].T  # (T, 20, 2) metres, v down
    radius = body.height * body.girth
    head = next(p for p in PARTS if p.name == "head")
    # Top of the head: the head capsule's far end, beyond the head joint along the neck-head bone.
    head_top = (head.t1 - 1.0) * body.lengths()["head"] + head.r1 * radius
    foot_r = max(p.r0 for p in PARTS if p.name.endswith("_foot")) * radius
    top = uv[:, _J["head"], 1] - head_top
    bottom = uv[:, :, 1].max(axis=1) + foot_r
    left, right = uv[:, :, 0].min(axis=1) - foot_r, uv[:, :, 0].max(axis=1) + foot_r
    scale = boxes[:, 3] / np.maximum(bottom - top, 1e-6)
    u0 = boxes[:, 0] + boxes[:, 2] / 2 - scale * (left + right) / 2
    v0 = boxes[:, 1] - scale * top
    out = np.stack([u0[:, None] + scale[:, None] * uv[:, :N_JOINTS, 0], v0[:, None] + scale[:, None] * uv[:, :N_JOINTS, 1]], -1)
    return out


def _cloud_paper(model: AppearanceModel, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All members of the matched clusters, each frame weighing the same (§3 step 4)."""
    offsets = model.member_offsets
    sizes = np.diff(offsets)[labels]
    rows = np.concatenate([np.arange(offsets[k], offsets[k + 1]) for k in labels])
    w = np.repeat(1.0 / sizes, sizes)
    return model.member_azimuth_deg[rows], model.member_elevation_deg[rows], w


def _cloud_exemplars(
    model: AppearanceModel, index: ExemplarIndex, bits: np.ndarray, dist: np.ndarray, config: EstimateConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Members of each frame's best clusters weighted by their own distance to the input."""
    offsets = model.member_offsets
    top = np.argsort(dist, axis=1)[:, : config.top_clusters]
    az, el, w = [], [], []
    for t in range(len(bits)):
        rows = np.concatenate([np.arange(offsets[k], offsets[k + 1]) for k in top[t]])
        d = hamming(bits[t : t + 1], index.bits[rows])[0]
        wt = np.exp(-(d - d.min()) / config.tau_view)
        az.append(index.azimuth_deg[rows])
        el.append(index.elevation_deg[rows])
        w.append(wt / wt.sum())
    return np.concatenate(az), np.concatenate(el), np.concatenate(w)


def _phase_distances(index: ExemplarIndex, bits: np.ndarray, vp: Viewpoint) -> np.ndarray:
    """Distance of each input to the nearest example of each phase at the viewpoint: (T, n_phases)."""
    rows = index.rows_at(vp.azimuth_deg, vp.elevation_deg)
    valid = rows >= 0
    d = hamming(bits, index.bits[np.maximum(rows, 0).ravel()]).reshape(len(bits), *rows.shape).astype(float)
    d[:, ~valid] = np.inf
    return d.min(axis=2)


def walker_score(model: AppearanceModel, silhouettes: list[np.ndarray]) -> np.ndarray:
    """How unlike a walker each silhouette is: eq. 8 distance to its nearest cluster mean."""
    registered, tf = model.register(silhouettes)
    d = distance(registered, model.means).min(axis=1).astype(float)
    d[~tf.valid] = np.inf
    return d


def clean_tracks(tracks: dict[str, CameraTrack], config: CleanupConfig | None = None, *,
                 score: Callable[[list[np.ndarray]], np.ndarray] | None = None
                 ) -> tuple[dict[str, CameraTrack], dict[str, CleanupReport]]:
    """Every camera's track reduced to the walker (:mod:`estimator.cleanup`).

    With a ``score`` (see :func:`walker_score`) a shadow or reflection joined
    to the feet is cut off too (:func:`estimator.cleanup.trim_below_feet`).
    """
    out, reports = {}, {}
    for name, t in tracks.items():
        sils, boxes, reports[name] = isolate_walker(
            t.silhouettes, t.boxes, image_size=t.image_size if t.full_frame else None, config=config)
        if score is not None:
            sils, boxes, reports[name].cut = trim_below_feet(sils, boxes, score, config=config)
        out[name] = CameraTrack(sils, boxes, full_frame=t.full_frame, image_size=t.image_size)
    return out, reports


def track_length(tracks: dict[str, CameraTrack]) -> int:
    """Frames of synchronized camera tracks; ValueError for no cameras or differing lengths."""
    if not tracks:
        raise ValueError("no cameras")
    lengths = {name: len(t.silhouettes) for name, t in tracks.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"cameras have different numbers of frames: {lengths}")
    return next(iter(lengths.values()))


def estimate_walk(
    tracks: dict[str, CameraTrack],
    model: AppearanceModel,
    *,
    config: EstimateConfig | None = None,
    gait: GaitModel | None = None,
) -> WalkEstimate:
    """Estimate phase per frame, 3D/2D joints and camera viewpoints for one window.

    Parameters
    ----------
    tracks : dict of str to CameraTrack
        Synchronized cameras; every track has the same number of frames T.
    model : AppearanceModel
    config : EstimateConfig, optional
    gait : GaitModel, optional
        Defaults to the shipped CMU fit.

    Raises
    ------
    ValueError
        No cameras, tracks of different lengths, or no silhouette at all.
    """
    config = config or EstimateConfig()
    gait = gait or load_gait()
    T = track_length(tracks)
    if T == 0 or all(s is None for t in tracks.values() for s in t.silhouettes):
        raise ValueError("no silhouettes in the window")
    n_phases = config.hmm.n_states
    exemplars = model.exemplars() if config.method == "exemplars" else None
    if exemplars is not None and exemplars.n_phases != n_phases:
        raise ValueError(f"exemplars have {exemplars.n_phases} phases, the HMM {n_phases}")

    reports: dict[str, CleanupReport] = {}
    if config.cleanup is not None:
        tracks, reports = clean_tracks(tracks, config.cleanup, score=lambda s: walker_score(model, s))
    cams: dict[str, CameraEstimate] = {}
    distances: dict[str, np.ndarray] = {}
    log_emission = np.zeros((T, n_phases))
    for name, track in tracks.items():
        present = np.array([k for k, s in enumerate(track.silhouettes) if s is not None], int)
        labels = np.full(T, -1, np.int64)
        dist = np.full((T, model.n_clusters), np.inf, np.float32)
        cam_notes = []
        cue = motion_cue(track.boxes) if track.full_frame else None
        note = reports[name].note() if name in reports else None
        if note:
            cam_notes.append(note)
        if not track.full_frame:
            cam_notes.append(
                "cropped silhouettes: no position in the full frame, so no motion cue (ahead/behind decided by "
                "the majority of matches), and joints2d are in each crop's own pixels"
            )
        if present.size:
            registered, tf = model.register([track.silhouettes[k] for k in present])
            ok = tf.valid
            present, registered = present[ok], registered[ok]
        if present.size == 0:
            cam_notes.append("no silhouette in this window")
            vp = Viewpoint(np.nan, np.nan, np.full((2, 2), np.nan), np.nan, "none", 0.0, 0)
            cams[name] = CameraEstimate(vp, cue, labels, np.full(T, np.nan), np.full((T, N_JOINTS, 2), np.nan), cam_notes,
                                        reports.get(name))
            distances[name] = dist
            continue
        d = distance(registered, model.means)
        dist[present] = d
        labels[present] = np.argmin(d, axis=1)
        distances[name] = dist
        obs = np.full(T, np.nan)
        if exemplars is None:
            vp = estimate_viewpoint(*_cloud_paper(model, labels[present]), cue=cue)
            for k in present:
                sl = slice(model.member_offsets[labels[k]], model.member_offsets[labels[k] + 1])
                near = (_abs_az_diff(model.member_azimuth_deg[sl], vp.azimuth_deg) <= config.phase_view_window_deg) & (
                    np.abs(model.member_elevation_deg[sl] - vp.elevation_deg) <= config.phase_view_window_deg
                )
                obs[k] = _circular_mean(model.member_phase[sl][near] if near.any() else model.member_phase[sl])
        else:
            bits = pack(registered)
            vp = estimate_viewpoint(*_cloud_exemplars(model, exemplars, bits, d, config), cue=cue)
            pd = _phase_distances(exemplars, bits, vp)
            log_emission[present] -= (pd - pd.min(axis=1, keepdims=True)) / config.tau_phase
            obs[present] = np.argmin(pd, axis=1) / n_phases
        cams[name] = CameraEstimate(vp, cue, labels, obs, np.full((T, N_JOINTS, 2), np.nan), cam_notes,
                                    reports.get(name))

    if all(c.viewpoint.n_samples == 0 for c in cams.values()):
        raise ValueError("no non-empty silhouette in the window")
    hmm = config.hmm
    if exemplars is None:
        log_prob, states = hmm.decode(np.stack([c.observations for c in cams.values()], axis=1))
    else:
        with np.errstate(divide="ignore"):
            log_prob, states = viterbi(np.log(hmm.startprob_), np.log(hmm.transmat_), log_emission)

    margin = 0.0
    if exemplars is None and config.resolve_half_cycle:
        states, margin = _resolve_half_cycle(model, states, cams, distances, n_phases)

    phase = states / n_phases
    skeleton = forward_kinematics(gait.angles(phase), config.body)
    person = skeleton - skeleton[:, :N_JOINTS].mean(axis=1, keepdims=True)
    for name, c in cams.items():
        if np.isfinite(c.viewpoint.azimuth_deg):
            placed = _place_joints(person, config.body, c.viewpoint, tracks[name].boxes)
            c.joints2d = np.where(np.isfinite(tracks[name].boxes[:, :1, None]), placed, np.nan)
    return WalkEstimate(
        phase=phase,
        states=states,
        joints3d=person[:, :N_JOINTS],
        cameras=cams,
        log_prob=log_prob,
        half_cycle_margin=margin,
        notes=[] if exemplars is not None else ["paper's path: cluster means only"],
        tracks=tracks,
    )


def _resolve_half_cycle(
    model: AppearanceModel, states: np.ndarray, cams: dict[str, CameraEstimate], distances: dict[str, np.ndarray], n_phases: int
) -> tuple[np.ndarray, float]:
    """Keep the Viterbi path or its half-cycle shift, whichever the clusters at (phase, viewpoint) fit better."""
    table, az_grid, el_grid = _example_lookup(model, n_phases)
    T = len(states)
    scores = [0.0, 0.0]
    for name, c in cams.items():
        if not np.isfinite(c.viewpoint.azimuth_deg):
            continue
        ai = int(np.argmin(_abs_az_diff(az_grid, c.viewpoint.azimuth_deg)))
        ei = int(np.argmin(np.abs(el_grid - c.viewpoint.elevation_deg)))
        d = []
        for shift in (0, n_phases // 2):
            lab = table[(states + shift) % n_phases, ai, ei]
            dd = distances[name][np.arange(T), np.maximum(lab, 0)].astype(float)
            dd[lab < 0] = np.inf
            d.append(dd)
        ok = np.isfinite(d[0]) & np.isfinite(d[1])  # both paths scored on the same frames
        scores[0] += float(d[0][ok].sum())
        scores[1] += float(d[1][ok].sum())
    if scores[1] < scores[0]:
        states = (states + n_phases // 2) % n_phases
    return states, abs(scores[0] - scores[1]) / max(min(scores), 1e-9)
