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
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from .appearance import AppearanceModel
from .body import PARTS
from .cleanup import (CleanupConfig, CleanupReport, astride_edge, check_plausible, edge_share, fixed_edge,
                      hidden_feet, on_bottom_edge, select_walker, trim_shadow)
from .camera import world_to_camera_rotation
from .exemplars import ExemplarIndex, pack
from .gait import GaitModel, load_gait
from .hmm import PhaseHMM, posterior, viterbi
from .joints import JOINT_NAMES, N_JOINTS
from .matchcache import Matched, MatchCache, derived, match, means_distance
from .occlusion import hidden_fraction, hidden_shares, whole_height
from .sequence import Sequence
from .skeleton import FULL_JOINT_NAMES, BodyShape, forward_kinematics
from .viewpoint import (FALL_MIN_ELEVATION_DEG, MotionCue, Viewpoint, azimuth_difference_deg, estimate_viewpoint,
                        head_band, motion_cue, with_path_elevation)

__all__ = ["CameraObservation", "CameraTrack", "EstimateConfig", "PhaseRefinement", "WalkEstimate", "clean_tracks",
           "concat_estimates", "decode_walk", "estimable_frames", "estimate_walk", "extrapolate_states",
           "observe_cameras", "prime_cache", "refine_cameras", "take_frames", "track_length", "tracks_from_sequence"]

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
    frame_outlier_mads : float
        Exemplar path: a frame whose distance to its nearest example exceeds
        the window's median by this many scaled MADs has no vote in the
        viewpoint (Tukey's biweight below); ``inf`` turns it off.
    vote_outlier_deg : float
        Exemplar path: a frame whose examples lie this far (on average) from
        the camera's viewpoint has no vote in it (biweight, iterated); ``inf``
        turns it off.
    phase_refine : bool
        Exemplar path: after the HMM, each camera's viewpoint again from the
        examples at the decoded phases, and the phases again.
    phase_shift_px : int
        ... comparing each input shifted by up to this many canvas pixels.
    settle_ahead_behind : bool
        Exemplar path, two cameras or more: where a camera's motion cue is
        contested (head and height disagree), absent, or rests on fewer than
        ``settle_few_frames`` frames while another camera was matched on that
        many or more, its ahead/behind is
        the one whose phase evidence agrees best with the other cameras'
        (:func:`_settle_ahead_behind`), by at least ``settle_margin`` of the
        HMM's log-probability per frame. Only cameras whose two sides are at
        least 60 deg apart (``|cos azimuth| >= settle_min_cos``) are settled
        so: nearer the walker's side the fold costs little.
    earlier_deg : float
        Given the azimuths a fixed camera was found at over earlier windows
        (``earlier``, the live service's smoothed viewpoints), a camera whose
        mirror across the ahead/behind fold is within this of its earlier
        azimuth, and its own viewpoint more than twice this away, takes the
        earlier side unless the other cameras' phase prefers its own by
        ``settle_margin`` (:func:`_settle_ahead_behind`); only while another
        camera, away from the walking axis, is where its earlier windows put
        it (:func:`_witness`: else the walker may have turned).
    settle_few_frames : int
        A camera's size change over a few frames tells ahead from behind less
        surely than the other cameras' phase: on exact silhouettes, of cameras
        seen on their first 4-8 frames of a 20-frame window 3-15 % were over 30
        deg off by their cue, 0-11 % by the phase (docs/ROBUSTNESS.md, "A
        camera on few frames").
    fall_min_elevation_deg : float
        Where a camera's growth is no evidence of ahead/behind, the feet's
        path in the image decides if its viewpoint is at least this far above
        the walker (:func:`estimator.viewpoint.estimate_viewpoint`); ``inf``
        never.
    path_elevation : bool
        Join each camera's elevation with the one its walker's image path
        implies (:func:`estimator.viewpoint.with_path_elevation`): the shape
        tells the elevation mostly by the legs, which a wall or the frame's
        edge may hide.
    out_of_step : float
        A camera whose phase observations are this far (cycles, median) from
        the phase decoded from two or more cameras gets a note that its
        viewpoint in the window is doubtful (:func:`phase_offset`; on the live
        composite walks such windows were 32 deg off in the median, the others
        5.5: docs/ROBUSTNESS.md, "A camera out of step"). It changes no estimate.
    min_frames : int
        Exemplar path: a camera whose walker was matched on fewer frames of the
        window than this, while another camera's was on this many, is set aside
        (:func:`_set_aside`): no viewpoint, phase nor joints from it in this
        window, and a note says why. On the live composite walks 4 of the 9
        windows x cameras on 5 frames or fewer were over 30 deg off, 1 of the
        14 on 6-9; on silhouettes damaged by every kind at once (two draws, 69
        cameras), a camera's first 3-5 frames of a 20-frame window 23-50 %
        (docs/ROBUSTNESS.md, "A camera on few frames").
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
    frame_outlier_mads: float = 3.0
    vote_outlier_deg: float = 45.0
    phase_refine: bool = True
    phase_shift_px: int = 1
    settle_ahead_behind: bool = True
    settle_margin: float = 0.5
    settle_min_cos: float = 0.5
    settle_few_frames: int = 10
    earlier_deg: float = 30.0
    fall_min_elevation_deg: float = FALL_MIN_ELEVATION_DEG
    path_elevation: bool = True
    out_of_step: float = 0.2
    min_frames: int = 6

    def __post_init__(self) -> None:
        if self.method not in ("exemplars", "paper"):
            raise ValueError(f"method must be 'exemplars' or 'paper', got {self.method!r}")
        if not (self.frame_outlier_mads > 0 and self.vote_outlier_deg > 0 and self.phase_shift_px >= 0):
            raise ValueError("frame_outlier_mads and vote_outlier_deg must be > 0 and phase_shift_px >= 0, got "
                             f"{self.frame_outlier_mads}, {self.vote_outlier_deg}, {self.phase_shift_px}")


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
    cut : ndarray of shape (T,), bool, optional
        Frames the clean-up cut below or beside the feet (a shadow or
        reflection removed, :func:`estimator.cleanup.trim_below_feet`,
        :func:`estimator.cleanup.trim_beside_feet`): the silhouette's outline
        at the feet there is the cut, not the body's
        (:mod:`estimator.frontier` leaves them out). None: not cleaned.
    hidden : ndarray of shape (T,), float, optional
        Share of the walker's height hidden below each frame's silhouette (by
        something in front, or the image's bottom edge; :mod:`estimator.occlusion`),
        0 where nothing is. None: not cleaned.
    """

    silhouettes: list[np.ndarray | None]
    boxes: np.ndarray
    full_frame: bool = True
    image_size: tuple[int, int] | None = None
    cut: np.ndarray | None = None
    hidden: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.boxes = np.asarray(self.boxes, dtype=float)
        if self.boxes.shape != (len(self.silhouettes), 4):
            raise ValueError(f"boxes must have shape ({len(self.silhouettes)}, 4), got {self.boxes.shape}")
        if self.cut is not None:
            self.cut = np.asarray(self.cut, bool)
            if self.cut.shape != (len(self.silhouettes),):
                raise ValueError(f"cut must have shape ({len(self.silhouettes)},), got {self.cut.shape}")
        if self.hidden is not None:
            self.hidden = np.asarray(self.hidden, float)
            if self.hidden.shape != (len(self.silhouettes),) or not np.all((self.hidden >= 0) & (self.hidden < 1)):
                raise ValueError(f"hidden must have shape ({len(self.silhouettes)},) and values in [0, 1)")

    def whole_heights(self) -> np.ndarray:
        """Each frame's walker height in pixels with what is hidden below (:attr:`hidden`): (T,)."""
        return whole_height(self.boxes[:, 3], 0.0 if self.hidden is None else self.hidden)

    def whole_boxes(self) -> np.ndarray:
        """:attr:`boxes` with the heights of :meth:`whole_heights` (the top row is the silhouette's): (T, 4)."""
        boxes = self.boxes.copy()
        boxes[:, 3] = self.whole_heights()
        return boxes

    def __getstate__(self) -> dict[str, Any]:
        """Pickled with 0/255 silhouettes packed to bits: tracks travel between the service's
        processes every live window (8x fewer bytes, less CPU to send and receive)."""
        state = dict(self.__dict__)
        state["silhouettes"] = [_pack_mask(m) for m in self.silhouettes]
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        state["silhouettes"] = [_unpack_mask(m) for m in state["silhouettes"]]
        self.__dict__.update(state)

    def take(self, frames) -> CameraTrack:
        """The track on ``frames`` (indices, or a slice) only."""
        idx = np.arange(len(self.silhouettes))[frames]
        return CameraTrack([self.silhouettes[k] for k in idx], self.boxes[idx], self.full_frame, self.image_size,
                           None if self.cut is None else self.cut[idx], None if self.hidden is None else self.hidden[idx])


def _pack_mask(mask: np.ndarray | None):
    """A uint8 0/255 mask as ``(shape, bits)``; anything else as it is."""
    if mask is None or mask.dtype != np.uint8 or mask.ndim != 2:
        return mask
    if np.count_nonzero(mask) != np.count_nonzero(mask == 255):
        return mask
    return mask.shape, np.packbits(mask)


def _unpack_mask(packed):
    if not isinstance(packed, tuple):
        return packed
    shape, bits = packed
    return np.unpackbits(bits, count=shape[0] * shape[1]).reshape(shape) * np.uint8(255)


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
    return pad_tracks(tracks)


def pad_tracks(tracks: dict[str, CameraTrack]) -> dict[str, CameraTrack]:
    """Every camera with the same number of frames: a camera's missing trailing frames are
    frames without data (as a missing file in a sequence folder)."""
    n = max((len(t.silhouettes) for t in tracks.values()), default=0)
    out = {}
    for name, t in tracks.items():
        k = n - len(t.silhouettes)
        out[name] = t if k == 0 else CameraTrack(
            list(t.silhouettes) + [None] * k, np.vstack([np.asarray(t.boxes, float).reshape(-1, 4),
                                                         np.full((k, 4), np.nan)]), t.full_frame, t.image_size)
    return out


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
    model_joints2d: np.ndarray | None = None  # the model's placement, when joints2d was measured
    posture_score: np.ndarray | None = None  # (T,) how well each measured posture explains its silhouette
    phase_offset: float | None = None  # out of step with the decoded phase (:func:`phase_offset`)


def phase_offset(observations: np.ndarray, phase: np.ndarray) -> float | None:
    """How far a camera walks out of step with the phase decoded from every camera: the median
    distance (cycles, 0-0.5) between its per-frame phase observations (NaN where none) and the
    decoded ``phase``; None with fewer than 3 observations. A camera whose viewpoint or silhouettes
    are wrong matches examples at other phases than the rest (``EstimateConfig.out_of_step``)."""
    seen = np.isfinite(observations)
    if seen.sum() < 3:
        return None
    return round(float(np.median(np.abs((observations[seen] - phase[seen] + 0.5) % 1.0 - 0.5))), 4)


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
    rig: Any = None  # estimator.rig.Rig, once calibrated (estimator.rig.calibrate_rig)
    phase_posterior: np.ndarray | None = None  # (T, n_states): the HMM's posterior (forward-backward)
    log_emission: np.ndarray | None = None  # (T, n_states): the phase evidence the HMM decoded

    def to_result(self, *, first_index: int = 0) -> dict:
        """The result format of DESIGN.md (JSON-able)."""
        cams = {}
        for name, c in self.cameras.items():
            d = c.viewpoint.to_dict()
            d["motion_cue"] = None if c.cue is None else {
                "growth_per_frame": round(c.cue.growth, 5),
                "growth_se": round(c.cue.growth_se, 5) if np.isfinite(c.cue.growth_se) else None,
                "growth_from": c.cue.source,
                "growth_contested": c.cue.conflict,
                "travel_heights_per_frame": round(c.cue.travel, 5),
            }
            d["phase_offset"] = c.phase_offset
            d["notes"] = c.notes
            cams[name] = d
        frames = []
        for t in range(len(self.phase)):
            j2d = {
                name: np.round(c.joints2d[t], 2).tolist()
                for name, c in self.cameras.items()
                if np.all(np.isfinite(c.joints2d[t]))
            }
            placed = {
                name: np.round(c.model_joints2d[t], 2).tolist()
                for name, c in self.cameras.items()
                if c.model_joints2d is not None and np.all(np.isfinite(c.model_joints2d[t]))
            }
            person = None if self.rig is None or self.rig.joints3d is None else self.rig.joints3d[t]
            seen = [name for name, c in self.cameras.items() if c.labels[t] >= 0]
            frames.append({
                "index": first_index + t,
                "phase": round(float(self.phase[t]), 4),
                "seen_by": seen,
                "predicted": not any(np.isfinite(c.observations[t]) for c in self.cameras.values()),
                **self._phase_belief(t),
                "joints3d": np.round(self.joints3d[t], 4).tolist(),
                **({} if person is None else {"person_joints3d": [
                    np.round(j, 4).tolist() if np.all(np.isfinite(j)) else None for j in person]}),
                "joints2d": j2d,
                "observed_phase": {
                    name: (None if np.isnan(c.observations[t]) else round(float(c.observations[t]), 4))
                    for name, c in self.cameras.items()
                },
                **({"model_joints2d": placed} if placed else {}),
            })
        return {
            "schema_version": RESULT_SCHEMA_VERSION,
            "units": RESULT_UNITS,
            "coordinate_frames": RESULT_FRAMES,
            "joint_names": list(JOINT_NAMES),
            "cameras": cams,
            "frames": frames,
            "hmm": {
                "log_prob": self.log_prob if np.isfinite(self.log_prob) else None,
                "half_cycle_margin": round(self.half_cycle_margin, 4) if np.isfinite(self.half_cycle_margin) else None,
            },
            "notes": self.notes + ([] if self.rig is None else self.rig.notes),
            **({} if self.rig is None else {"rig": self.rig.to_dict(), "body": self.rig.body_dict()}),
        }


    def _phase_belief(self, t: int) -> dict:
        """``phase_confidence`` (posterior mass within one state of the reported phase) and
        ``phase_posterior`` of frame ``t``; nothing without a posterior."""
        if self.phase_posterior is None:
            return {}
        post = self.phase_posterior[t]
        k = len(post)
        near = (int(self.states[t]) + np.arange(-1, 2)) % k
        return {"phase_confidence": round(float(post[near].sum()), 4),
                "phase_posterior": np.round(post, 4).tolist()}


RESULT_SCHEMA_VERSION = 1
"""Version of the result's layout (docs/FORMATS.md); raised when a key changes meaning or goes."""

RESULT_UNITS = {"joints3d": "m", "person_joints3d": "m", "joints2d": "px", "model_joints2d": "px",
                "phase": "cycles", "azimuth_deg": "deg", "elevation_deg": "deg", "focal_px": "px",
                "centre_m": "m", "segments": "m"}
"""Units of the result's fields."""

RESULT_FRAMES = {
    "joints3d": "person frame: x walking direction, y the walker's left, z up; centred on the 13 joints",
    "person_joints3d": "person frame: x the way the body faces, y its left, z up (trunk); centred on the 13 joints",
    "joints2d": "each camera's full-frame image: u right, v down, pixel centres at integers, origin top-left",
    "rig.rotation": "R_c R_ref^T: rows the camera's image u, image v and viewing direction, in the reference camera's",
    "rig.centre_m": "the reference camera's frame: x right, y down, z forward",
    "azimuth_deg": "the walker's frame, from the direction the walker faces, counter-clockwise seen from above",
}
"""The frame each coordinate field is expressed in (docs/FORMATS.md, Coordinate frames)."""


def take_frames(estimate: WalkEstimate, frames: np.ndarray) -> WalkEstimate:
    """The estimate on ``frames`` (indices into its window) only: every per-frame array sliced."""
    idx = np.asarray(frames, int)

    def cut(a):
        return None if a is None else np.asarray(a)[idx]

    cams = {n: replace(c, labels=cut(c.labels), observations=cut(c.observations), joints2d=cut(c.joints2d),
                       model_joints2d=cut(c.model_joints2d), posture_score=cut(c.posture_score))
            for n, c in estimate.cameras.items()}
    tracks = None if estimate.tracks is None else {n: t.take(idx) for n, t in estimate.tracks.items()}
    return replace(estimate, phase=cut(estimate.phase), states=cut(estimate.states), joints3d=cut(estimate.joints3d),
                   cameras=cams, tracks=tracks, phase_posterior=cut(estimate.phase_posterior), rig=None)


def concat_estimates(estimates: list[WalkEstimate]) -> WalkEstimate:
    """Estimates of successive stretches of one walk joined in time (e.g. frames of several live
    windows, for a rig solved over all of them with fixed cameras). Each camera's viewpoint is the
    medoid of the stretches' (the one nearest all the others: a stretch whose viewpoint flipped
    does not decide it), its notes the last stretch's; a camera absent from a stretch has no data
    there."""
    if not estimates:
        raise ValueError("nothing to join")
    names = list(dict.fromkeys(n for e in estimates for n in e.cameras))
    lengths = [len(e.phase) for e in estimates]

    def per_camera(name: str, get, fill_shape: tuple, fill=np.nan) -> np.ndarray:
        parts = []
        for e, n in zip(estimates, lengths):
            c = e.cameras.get(name)
            v = None if c is None else get(c)
            parts.append(np.asarray(v, float) if v is not None else np.full((n, *fill_shape), fill))
        return np.concatenate(parts)

    cams = {}
    for name in names:
        last = next(e.cameras[name] for e in reversed(estimates) if name in e.cameras)
        measured = any(name in e.cameras and e.cameras[name].model_joints2d is not None for e in estimates)
        cams[name] = replace(
            last, viewpoint=_medoid([e.cameras[name].viewpoint for e in estimates if name in e.cameras]),
            labels=per_camera(name, lambda c: c.labels, (), -1).astype(int),
            observations=per_camera(name, lambda c: c.observations, ()),
            joints2d=per_camera(name, lambda c: c.joints2d, (N_JOINTS, 2)),
            model_joints2d=per_camera(name, lambda c: c.model_joints2d, (N_JOINTS, 2)) if measured else None,
            posture_score=per_camera(name, lambda c: c.posture_score, ()) if measured else None)
    tracks = None
    if all(e.tracks is not None for e in estimates):
        tracks = {}
        for name in names:
            sils, boxes, cuts, hidden, ref = [], [], [], [], None
            for e, n in zip(estimates, lengths):
                t = e.tracks.get(name)
                sils += [None] * n if t is None else list(t.silhouettes)
                boxes.append(np.full((n, 4), np.nan) if t is None else t.boxes)
                cuts.append(np.zeros(n, bool) if t is None or t.cut is None else t.cut)
                hidden.append(np.zeros(n) if t is None or t.hidden is None else t.hidden)
                ref = t or ref
            tracks[name] = CameraTrack(sils, np.concatenate(boxes), ref.full_frame, ref.image_size, np.concatenate(cuts),
                                       np.concatenate(hidden))
    posts = [e.phase_posterior for e in estimates]
    phase = np.concatenate([e.phase for e in estimates])
    for c in cams.values():  # over the joined stretches (the notes stay the last stretch's)
        c.phase_offset = phase_offset(c.observations, phase) if c.phase_offset is not None else None
    return WalkEstimate(
        phase=phase, states=np.concatenate([e.states for e in estimates]),
        joints3d=np.concatenate([e.joints3d for e in estimates]), cameras=cams,
        log_prob=float(sum(e.log_prob for e in estimates)), half_cycle_margin=estimates[-1].half_cycle_margin,
        notes=list(estimates[-1].notes), tracks=tracks,
        phase_posterior=np.concatenate(posts) if all(p is not None for p in posts) else None)


def _medoid(viewpoints: list[Viewpoint]) -> Viewpoint:
    """The viewpoint with the least summed angular distance (azimuth on the circle, elevation) to the others."""
    ok = [v for v in viewpoints if np.isfinite(v.azimuth_deg) and np.isfinite(v.elevation_deg)]
    if not ok:
        return viewpoints[-1]
    az = np.array([v.azimuth_deg for v in ok])
    el = np.array([v.elevation_deg for v in ok])
    cost = np.abs(azimuth_difference_deg(az[:, None], az[None, :])) + np.abs(el[:, None] - el[None, :])
    return ok[int(np.argmin(cost.sum(axis=1)))]


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


def _member_rows(model: AppearanceModel, clusters: np.ndarray) -> np.ndarray:
    """Rows (in the exemplar index) of the members of ``clusters``, in that order."""
    offsets = model.member_offsets
    return np.concatenate([np.arange(offsets[k], offsets[k + 1]) for k in clusters])


def _member_distances(model: AppearanceModel, index: ExemplarIndex, bits: np.ndarray, dist: np.ndarray,
                      top_clusters: int, cache: MatchCache | None = None, keys: list[bytes] | None = None
                      ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per input: the rows of the members of its ``top_clusters`` nearest cluster means
    (``dist`` to the means) and the eq. 8 distance of the input to each of them (kept in ``cache``
    under the inputs' ``keys``)."""
    top = np.argsort(dist, axis=1)[:, :top_clusters]

    def compute(todo: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        rows = [_member_rows(model, top[t]) for t in todo]
        return [(r, _hamming(bits[t : t + 1], index.bits[r])[0]) for t, r in zip(todo, rows)]

    pairs = derived(cache, keys, len(bits), ("members", top_clusters), compute)
    return [p[0] for p in pairs], [p[1] for p in pairs]


def _cloud_paper(model: AppearanceModel, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All members of the matched clusters, each frame weighing the same (§3 step 4)."""
    sizes = np.diff(model.member_offsets)[labels]
    rows = _member_rows(model, labels)
    w = np.repeat(1.0 / sizes, sizes)
    return model.member_azimuth_deg[rows], model.member_elevation_deg[rows], w


@dataclass
class _Cloud:
    """Example viewpoints voted for by a camera's frames (§3 step 4).

    ``w`` sums to 1 over each frame's members; ``frame`` is each member's
    frame (index into the registered inputs); ``best`` each frame's distance
    to its nearest example.
    """

    az: np.ndarray
    el: np.ndarray
    w: np.ndarray
    frame: np.ndarray
    best: np.ndarray


_CLOUD_REACH = 10.0  # a frame's cloud: its examples within this many tau_view of its best


def _hamming(queries: np.ndarray, bank: np.ndarray) -> np.ndarray:
    """:func:`estimator.exemplars.hamming`: every query against every bank row, (Q, B) x (R, B) -> (Q, R)."""
    return _hamming_pairs(queries[:, None, :], bank[None, :, :])


def _hamming_pairs(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Pixel disagreements of packed silhouettes paired element-wise (broadcast over leading
    axes), on 64-bit words when the rows allow."""
    if a.shape[-1] % 8:
        return np.bitwise_count(a ^ b).sum(axis=-1, dtype=np.int64)
    return np.bitwise_count(np.ascontiguousarray(a).view(np.uint64) ^ np.ascontiguousarray(b).view(np.uint64)
                            ).sum(axis=-1, dtype=np.int64)


def _cloud(index: ExemplarIndex, frame_rows: list[np.ndarray], distances: list[np.ndarray],
           config: EstimateConfig) -> _Cloud:
    """The cloud of each frame's candidate examples (rows of ``index``) weighted by ``exp(-d / tau_view)``.

    Members whose weight is below ``exp(-_CLOUD_REACH)`` of their frame's best are left out.
    """
    az, el, w, frame, best = [], [], [], [], np.empty(len(frame_rows))
    for t, (rows, d) in enumerate(zip(frame_rows, distances)):
        best[t] = d.min()
        keep = d - best[t] <= _CLOUD_REACH * config.tau_view
        wt = np.exp(-(d[keep] - best[t]) / config.tau_view)
        az.append(index.azimuth_deg[rows[keep]])
        el.append(index.elevation_deg[rows[keep]])
        w.append(wt / wt.sum())
        frame.append(np.full(int(keep.sum()), t))
    return _Cloud(np.concatenate(az), np.concatenate(el), np.concatenate(w), np.concatenate(frame), best)


def _cloud_exemplars(model: AppearanceModel, index: ExemplarIndex, bits: np.ndarray, dist: np.ndarray,
                     config: EstimateConfig, cache: MatchCache | None = None, keys: list[bytes] | None = None
                     ) -> _Cloud:
    """Members of each frame's best clusters weighted by their own distance to the input."""
    return _cloud(index, *_member_distances(model, index, bits, dist, config.top_clusters, cache, keys), config)


def _rows_by_phase(index: ExemplarIndex) -> list[np.ndarray]:
    """Rows of ``index`` at each of its phases (every viewpoint and body)."""
    p = np.round(index.phase * index.n_phases).astype(int) % index.n_phases
    return [np.flatnonzero(p == k) for k in range(index.n_phases)]


def _cloud_at_phases(index: ExemplarIndex, by_phase: list[np.ndarray], registered: np.ndarray, states: np.ndarray,
                     config: EstimateConfig, cache: MatchCache | None = None, keys: list[bytes] | None = None
                     ) -> _Cloud:
    """Each frame's examples at its decoded phase, from every viewpoint, weighted by their distance.

    The §5 registration puts the centroid of a silhouette at the canvas
    centre; a hole or a missing forearm moves the centroid, so the distance
    to an example is the least over shifts of the input by up to
    ``config.phase_shift_px`` canvas pixels along either axis
    (:func:`_distances_at_phases`). A frame's distances at a phase are kept in
    ``cache`` under its key (the next window decodes it at the same phase).
    """
    r = config.phase_shift_px
    reach = _CLOUD_REACH * config.tau_view
    tags = [("phase", int(k), r, reach) for k in states]
    dists = derived(cache, keys, len(registered), tags,
                    lambda todo: _distances_at_phases(index, by_phase, registered[todo], states[todo], r, reach))
    return _cloud(index, [by_phase[int(k)] for k in states], dists, config)


def _distances_at_phases(index: ExemplarIndex, by_phase: list[np.ndarray], registered: np.ndarray,
                         states: np.ndarray, r: int, reach: float) -> list[np.ndarray]:
    """Distance of each registered input to each example at its phase (``by_phase[state]``), the
    least over shifts of the input by up to ``r`` canvas pixels along either axis: per input an
    int32 row.

    The shifts are tried only where they can matter (exact, by the triangle
    inequality): an example whose unshifted distance ``d0`` exceeds the
    input's least ``d0`` plus ``reach`` plus ``H(shifted, unshifted)``
    cannot come within the reach by that shift. Examples out of reach keep
    their unshifted distance.
    """
    shifts = [(0, 0)] + [(d, 0) for d in range(-r, r + 1) if d] + [(0, d) for d in range(-r, r + 1) if d]
    S = len(shifts)
    moved = pack(np.stack([np.roll(registered, sh, axis=(1, 2)) for sh in shifts], axis=1)
                 .reshape(len(registered) * S, *registered.shape[1:])).reshape(len(registered), S, -1)
    moved_by = _hamming_pairs(moved[:, 1:], moved[:, :1])  # (inputs, S - 1): H(shifted, unshifted)
    out: list[np.ndarray] = [None] * len(registered)
    for k in np.unique(states):  # the inputs at one phase share their examples
        frames = np.flatnonzero(states == k)
        bank = index.bits[by_phase[int(k)]]
        d0 = _hamming(moved[frames, 0], bank)  # (frames, examples)
        d, bound = d0.copy(), d0.min(axis=1, keepdims=True) + reach
        for s in range(1, S):
            f, e = np.nonzero(d0 - moved_by[frames, s - 1, None] <= bound)
            if f.size:
                d[f, e] = np.minimum(d[f, e], _hamming_pairs(moved[frames[f], s], bank[e]))
        for i, t in enumerate(frames):
            out[t] = d[i].astype(np.int32)
    return out


def _fold_distance(az: np.ndarray, centre: float) -> np.ndarray:
    """Angle from ``centre`` to the nearer of ``az`` and its ahead/behind mirror ``180 - az`` (degrees):
    the viewpoint fit folds the cloud onto one side, so a vote on the other is not an outlier for that."""
    return np.minimum(_abs_az_diff(az, centre), _abs_az_diff(180.0 - az, centre))


def _biweight(u: np.ndarray) -> np.ndarray:
    """Tukey's biweight ``(1 - u^2)^2`` for ``|u| < 1``, else 0."""
    return np.where(np.abs(u) < 1.0, (1.0 - u**2) ** 2, 0.0)


def _vote(cloud: _Cloud, n_frames: int, cue: MotionCue | None, config: EstimateConfig,
          iterations: int = 3, ahead: bool | None = None) -> tuple[Viewpoint, np.ndarray]:
    """The viewpoint of a camera's cloud with outlying frames voting less; and each frame's weight.

    Each frame votes with weight 1 in the paper's fit (§3 step 4), so a few
    frames whose silhouette is damaged (a cut limb, holes: their nearest
    examples are seen from elsewhere) pull the mean as far as they like. Two
    robust weights (Tukey's biweight, an M-estimator of the cloud's centre):

    - **match**: a frame whose distance to its nearest example exceeds the
      window's median by ``frame_outlier_mads`` scaled MADs counts for nothing;
    - **vote**: a frame whose members lie on average ``vote_outlier_deg`` from
      the estimate (either side of the ahead/behind fold) counts for nothing;
      iterated from the fit with the match weights.
    """
    weight = np.ones(n_frames)
    if np.isfinite(config.frame_outlier_mads):
        med = np.median(cloud.best)
        mad = 1.4826 * np.median(np.abs(cloud.best - med))
        weight = _biweight(np.maximum(cloud.best - med, 0.0) / max(config.frame_outlier_mads * mad, 1e-9))
        if weight.sum() <= 0:
            weight = np.ones(n_frames)
    vote = dict(cue=cue, ahead=ahead, fall_min_elevation_deg=config.fall_min_elevation_deg)
    vp = estimate_viewpoint(cloud.az, cloud.el, cloud.w * weight[cloud.frame], **vote)
    if np.isfinite(config.vote_outlier_deg):
        match = weight
        for _ in range(iterations):
            off = np.bincount(cloud.frame, cloud.w * _fold_distance(cloud.az, vp.azimuth_deg), minlength=n_frames)
            w = match * _biweight(off / config.vote_outlier_deg)
            if w.sum() <= 0:
                break
            weight = w
            vp = estimate_viewpoint(cloud.az, cloud.el, cloud.w * weight[cloud.frame], **vote)
    return vp, weight


def _phase_distances(index: ExemplarIndex, bits: np.ndarray, vp: Viewpoint, cache: MatchCache | None = None,
                     keys: list[bytes] | None = None) -> np.ndarray:
    """Distance of each input to the nearest example of each phase at the viewpoint: (T, n_phases).

    Taken per grid viewpoint near ``vp`` (the least over them), each kept in
    ``cache`` under the input's key: the re-vote and the next window look at
    most of the same grid viewpoints.
    """
    best = np.full((len(bits), index.n_phases), np.inf)
    for cell in index.cells_at(vp.azimuth_deg, vp.elevation_deg):
        rows = index.rows_in_cell(cell)

        def compute(todo: np.ndarray, rows: np.ndarray = rows) -> np.ndarray:
            d = _hamming(bits[todo], index.bits[np.maximum(rows, 0).ravel()]).reshape(len(todo), *rows.shape)
            return np.where(rows >= 0, d, np.inf).min(axis=2)

        best = np.minimum(best, np.stack(derived(cache, keys, len(bits), ("cell", *cell), compute)))
    return best


def walker_score(model: AppearanceModel, silhouettes: list[np.ndarray], *, top_clusters: int = 3,
                 cache: MatchCache | None = None) -> np.ndarray:
    """How unlike a walker each silhouette is: eq. 8 (Hamming) distance to the nearest example
    among the members of its ``top_clusters`` nearest cluster means; inf where it cannot be registered.

    The members rather than the means: a silhouette cut through the legs is
    about as far from the nearest (blurred) mean as a whole one, but much
    farther from every sharp example (docs/ROBUSTNESS.md). With a ``cache`` each
    silhouette is registered and scored once (:mod:`estimator.matchcache`).
    """
    m = match(model, silhouettes, cache)
    return _nearest_member(model, m.registered, m.valid, m.means_distance, top_clusters, cache, m.keys)


def registered_walker_score(model: AppearanceModel, registered: np.ndarray, valid: np.ndarray, *,
                            top_clusters: int = 3) -> np.ndarray:
    """:func:`walker_score` of silhouettes already registered with ``model`` ((N, h, w), 0/1; inf
    where not ``valid``): the share search of :func:`estimator.occlusion.hidden_fraction`
    registers each silhouette at every share at once."""
    return _nearest_member(model, registered, valid, means_distance(model, registered, valid), top_clusters)


def _nearest_member(model: AppearanceModel, registered: np.ndarray, valid: np.ndarray, means_distance: np.ndarray,
                    top_clusters: int, cache: MatchCache | None = None, keys: list[bytes] | None = None
                    ) -> np.ndarray:
    """Each registered input's eq. 8 distance to the nearest member of its ``top_clusters`` nearest
    clusters; inf where not ``valid``."""
    out = np.full(len(registered), np.inf)
    rows = np.flatnonzero(valid)
    if rows.size:
        _, dists = _member_distances(model, model.exemplars(), pack(registered[rows]), means_distance[rows],
                                     top_clusters, cache, None if keys is None else [keys[i] for i in rows])
        out[rows] = [d.min() for d in dists]
    return out


def clean_tracks(tracks: dict[str, CameraTrack], config: CleanupConfig | None = None, *,
                 score: Callable[[list[np.ndarray]], np.ndarray] | None = None
                 ) -> tuple[dict[str, CameraTrack], dict[str, CleanupReport]]:
    """Every camera's track reduced to the walker (:mod:`estimator.cleanup`).

    The walker is selected (:func:`estimator.cleanup.select_walker`); with a
    ``score`` (see :func:`walker_score`) a shadow or reflection joined to the
    feet is cut off, below or beside them (:func:`estimator.cleanup.trim_shadow`); then frames
    whose walker is implausible are skipped (:func:`estimator.cleanup.check_plausible`:
    after the cut, so that a shadow reaching the image border does not count
    as the walker cut by it). A walker hidden below, by something in front
    (:func:`estimator.cleanup.hidden_feet`) or by the image's bottom edge, is
    said in the report's ``hidden_by``; :func:`observe_cameras` matches it by
    its visible part.
    """
    config = config or CleanupConfig()
    out, reports = {}, {}
    for name, t in tracks.items():
        sils, boxes, report = select_walker(t.silhouettes, t.boxes, config=config)
        cut, front = np.zeros(len(sils), bool), False
        if score is not None:
            sils, boxes, kept, beside = trim_shadow(sils, boxes, score, config=config)
            below = kept < 1.0
            cut = beside | below
            report.side_cut = int(beside.sum())
            report.cut, report.cut_kept = int(below.sum()), float(np.median(kept[below])) if below.any() else 1.0
            front = not below.any() and hidden_feet(sils, score, config=config) > 0  # a cut below the feet ends flat too
        sils, boxes, reports[name] = check_plausible(sils, boxes, report,
                                                     image_size=t.image_size if t.full_frame else None, config=config)
        if score is not None and t.full_frame and not below.any():  # on the frames of a plausible walker
            report.on_edge = fixed_edge(sils, boxes, config=config)
            report.astride = astride_edge(sils, boxes, report.on_edge)
            front = front or report.fixed_edge
        if t.full_frame and t.image_size is not None and on_bottom_edge(boxes, t.image_size):
            report.hidden_by = "the image's bottom edge"
        elif front:
            report.hidden_by = "something in front"
        out[name] = CameraTrack(sils, boxes, full_frame=t.full_frame, image_size=t.image_size, cut=cut)
    return out, reports


def estimable_frames(tracks: dict[str, CameraTrack]) -> int:
    """The frames of a window that has something to estimate (:func:`track_length`); ValueError for
    no cameras, tracks of different lengths, or no silhouette at all."""
    T = track_length(tracks)
    if T == 0 or all(s is None for t in tracks.values() for s in t.silhouettes):
        raise ValueError("no silhouettes in the window")
    return T


def track_length(tracks: dict[str, CameraTrack]) -> int:
    """Frames of synchronized camera tracks; ValueError for no cameras or differing lengths."""
    if not tracks:
        raise ValueError("no cameras")
    lengths = {name: len(t.silhouettes) for name, t in tracks.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(f"cameras have different numbers of frames: {lengths}")
    return next(iter(lengths.values()))


@dataclass
class CameraObservation:
    """One camera's evidence over a window, before the cameras are joined (:func:`observe_cameras`).

    ``registered`` and ``bits`` are what the phase-given refine
    (:func:`refine_cameras`) compares with the examples; they can stay where
    they were computed (:meth:`light` drops them), the rest is what the joint
    decoding (:func:`decode_walk`) needs.
    """

    estimate: CameraEstimate
    track: CameraTrack  # after the clean-up
    distances: np.ndarray  # (T, n_clusters) eq. 8 to the cluster means, inf where none
    present: np.ndarray  # frames with a matched silhouette
    evidence: np.ndarray | None = None  # (len(present), n_phases) phase costs at the viewpoint; exemplars only
    mirror: tuple[Viewpoint, np.ndarray, np.ndarray] | None = None  # the other side's (viewpoint, evidence, obs)
    registered: np.ndarray | None = None
    bits: np.ndarray | None = None
    keys: list[bytes] | None = None  # the present frames' silhouettes in the match cache

    def light(self) -> CameraObservation:
        """The observation without what only :func:`refine_cameras` needs (the registered
        silhouettes and their cache keys): what the joint decoding is sent."""
        return replace(self, registered=None, bits=None, keys=None)


@dataclass
class PhaseRefinement:
    """One camera's viewpoint voted again at the decoded phases (:func:`refine_cameras`)."""

    viewpoint: Viewpoint
    observations: np.ndarray  # (T,)
    evidence: np.ndarray  # (len(present), n_phases)
    outliers: int  # frames that count less


def _cleaned(tracks: dict[str, CameraTrack], model: AppearanceModel, config: EstimateConfig,
             cache: MatchCache | None, *, hidden: bool = True) -> tuple[dict[str, CameraTrack], dict[str, CleanupReport]]:
    """The tracks after the clean-up ``config`` asks for (:func:`clean_tracks`, shadows scored
    with ``cache``), and its reports; as they are without one. With ``hidden``, the share of
    the body hidden below a camera's walker is searched (:func:`estimator.occlusion.hidden_fraction`)."""
    if config.cleanup is None:
        return tracks, {}
    tracks, reports = clean_tracks(tracks, config.cleanup, score=lambda s: walker_score(model, s, cache=cache))
    for name, report in reports.items():
        if hidden and report.hidden_by:
            tracks[name] = _hidden_below(tracks[name], report, model, config.cleanup)
    return tracks, reports


def _hidden_below(t: CameraTrack, report: CleanupReport, model: AppearanceModel,
                  config: CleanupConfig) -> CameraTrack:
    """A camera's track with the share of the walker hidden below each frame (``hidden``), its
    ``report`` filled in (the window's share, or nothing hidden after all)."""
    edge = report.on_edge if report.fixed_edge else np.ones(len(t.silhouettes), bool)
    report.hidden, _ = hidden_fraction(model, [s if e else None for s, e in zip(t.silhouettes, edge)],
                                       config.hidden_matched, score=registered_walker_score,
                                       frames=config.cut_frames)
    past = report.past_edge()
    by_heights = edge_share(t.boxes, edge, whole=past) if past is not None else np.nan
    if not report.hidden or abs(by_heights - report.hidden) > config.edge_agree:
        # A whole body fits best (a shadow at the edge, flat feet), or the walker's frames past the
        # edge's end say another share than the examples do: a walker whose feet rest on one row.
        report.hidden_by, report.hidden, report.on_edge, report.astride = "", 0.0, None, None
        return t
    behind = edge & np.array([s is not None for s in t.silhouettes])
    share = np.where(behind, report.hidden, 0.0)
    if report.fixed_edge:  # each frame its own share: the walker's size from what shows it, not the edge
        cue = _cue(t.silhouettes, t.boxes, report)
        if cue is not None and np.isfinite(cue.growth_se):
            shares = hidden_shares(t.boxes[:, 3], cue.growth, report.hidden, whole=report.past_edge(half=False))
            share = np.where(behind, np.nan_to_num(shares, nan=report.hidden), 0.0)
    # The outline's bottom there is the wall's or the frame's (estimator.frontier leaves it out).
    return replace(t, cut=t.cut | behind, hidden=share)


def _cue(silhouettes: list[np.ndarray | None], boxes: np.ndarray, report: CleanupReport | None) -> MotionCue | None:
    """A camera's :func:`~estimator.viewpoint.motion_cue` after its clean-up ``report``: behind an
    edge fixed in the image, the heights of the frames past its end
    (:meth:`~estimator.cleanup.CleanupReport.past_edge`), else the head's width and path alone."""
    band = head_band(silhouettes, boxes)
    if report is None:
        return motion_cue(boxes, band.points)
    if not report.fixed_edge:
        return motion_cue(boxes, band.points, feet_cut=report.cut > 0 or report.hidden > 0)
    past = report.past_edge()
    return motion_cue(boxes, band.points, feet_cut=report.cut > 0, heights=False if past is None else past,
                      head_widths=band.widths)


def _camera_model(model: AppearanceModel, report: CleanupReport | None) -> AppearanceModel:
    """The model a camera's walker is matched with: cut for a walker hidden below
    (:meth:`AppearanceModel.hidden_below`), else ``model``."""
    return model.hidden_below(report.hidden) if report is not None and report.hidden else model


def _camera_cache(cache: MatchCache | None, model: AppearanceModel, whole: AppearanceModel) -> MatchCache | None:
    """The cache a camera matched with ``model`` uses: ``cache`` for the ``whole`` model it is bound
    to, or its cache for a cut model (:meth:`MatchCache.for_cut`)."""
    return cache if cache is None or model is whole else cache.for_cut(model)


def _matched(track: CameraTrack, model: AppearanceModel, cache: MatchCache | None,
             whole: AppearanceModel | None = None
             ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None, list[bytes] | None]:
    """A camera's frames with a silhouette that registers, their registered silhouettes, eq. 8
    distances to the cluster means and cache keys (:func:`~estimator.matchcache.match`).

    A camera matched with a cut ``model`` whose walker passed the end of the edge on some frames
    (``track.hidden`` 0 there): those are registered whole, from the uncut ``whole`` model, and
    compared on the same rows (:meth:`~estimator.appearance.AppearanceModel.hidden_below`'s
    ``compared``), so that every frame's distances are alike.
    """
    present = np.array([k for k, s in enumerate(track.silhouettes) if s is not None], int)
    if not present.size:
        return present, None, None, None
    sils = [track.silhouettes[k] for k in present]
    shown = None if whole is None or model.hidden is None or track.hidden is None else track.hidden[present] == 0
    if shown is None or not shown.any():
        m = match(model, sils, cache)
    else:
        m = Matched(np.empty((len(sils), *model.size), np.float32), np.empty(len(sils), bool),
                    np.empty((len(sils), model.n_clusters), np.float32), None)
        for pick, by in ((shown, whole.hidden_below(0.0, compared=model.hidden.fraction)), (~shown, model)):
            if pick.any():
                part = match(by, [s for s, p in zip(sils, pick) if p])
                m.registered[pick], m.valid[pick], m.means_distance[pick] = \
                    part.registered, part.valid, part.means_distance
    keys = None if m.keys is None else [k for k, v in zip(m.keys, m.valid) if v]
    return present[m.valid], m.registered[m.valid], m.means_distance[m.valid], keys


def _no_viewpoint() -> Viewpoint:
    """The viewpoint of a camera that observed nothing."""
    return Viewpoint(np.nan, np.nan, np.full((2, 2), np.nan), np.nan, "none", 0.0, 0)


def _set_aside(o: CameraObservation, note: str) -> CameraObservation:
    """``o`` as a camera that observed nothing in the window: no viewpoint, phase observations
    nor joints, ``note`` added to its notes (its clean-up and motion cue kept)."""
    c = o.estimate
    T = len(c.labels)
    cam = replace(c, viewpoint=_no_viewpoint(), labels=np.full(T, -1, np.int64), observations=np.full(T, np.nan),
                  joints2d=np.full((T, N_JOINTS, 2), np.nan), notes=[*c.notes, note])
    return CameraObservation(cam, o.track, o.distances, np.empty(0, np.int64))


def _few_frames(observations: dict[str, CameraObservation], least: int) -> dict[str, CameraObservation]:
    """``observations`` with the cameras matched on fewer than ``least`` frames set aside
    (:func:`_set_aside`) when another camera was matched on ``least`` or more
    (``EstimateConfig.min_frames``)."""
    if not any(o.present.size >= least for o in observations.values()):
        return observations
    return {name: _set_aside(o, f"the walker was matched on {o.present.size} frames of this window, fewer than "
                                f"{least} where another camera has them: too few for a viewpoint, so none")
            if 0 < o.present.size < least else o for name, o in observations.items()}


def _few(config: EstimateConfig, camera: CameraEstimate) -> bool:
    """Whether a camera's motion cue rests on fewer than ``config.settle_few_frames`` frames."""
    return camera.cue is not None and camera.cue.n_frames < config.settle_few_frames


def _settles(config: EstimateConfig, camera: CameraEstimate, earlier: float | None = None) -> bool:
    """Whether a camera's ahead/behind may be open to the other cameras' phase (:func:`_settle_ahead_behind`):
    its motion cue is contested, absent or rests on few frames (:func:`_few`), or the ``earlier``
    windows put it on the other side (:func:`_against_earlier`)."""
    return (config.settle_ahead_behind and np.isfinite(camera.viewpoint.azimuth_deg)
            and (_contested(camera) or _few(config, camera) or _against_earlier(config, camera, earlier))
            and abs(np.cos(np.deg2rad(camera.viewpoint.azimuth_deg))) >= config.settle_min_cos)


def _against_earlier(config: EstimateConfig, camera: CameraEstimate, earlier: float | None) -> bool:
    """Whether a fixed camera's earlier windows found it (azimuth ``earlier``) on the other side of the
    ahead/behind fold from this window's viewpoint: its mirror within ``config.earlier_deg`` of it,
    its own side more than twice that away."""
    if earlier is None or not np.isfinite(earlier):
        return False
    return (_az_diff(camera, earlier, mirrored=True) <= config.earlier_deg
            and _az_diff(camera, earlier) > 2 * config.earlier_deg)


def _witness(config: EstimateConfig, camera: CameraEstimate, earlier: float | None) -> bool:
    """Whether a camera tells that the walker keeps the heading of the earlier windows: it is within
    ``config.earlier_deg`` of where they found it, and that is more than as far from the walking axis.
    Near the axis a turn and the fold look alike (``a + 180`` against ``180 - a``): two such cameras,
    one folded, once held the other to the heading before a turn."""
    return (earlier is not None and np.isfinite(earlier) and _az_diff(camera, earlier) <= config.earlier_deg
            and abs(np.sin(np.deg2rad(earlier))) > np.sin(np.deg2rad(config.earlier_deg)))


def _az_diff(camera: CameraEstimate, azimuth: float, *, mirrored: bool = False) -> float:
    """How far (deg) a camera's viewpoint, or its mirror across the ahead/behind fold, is from ``azimuth``."""
    a = camera.viewpoint.azimuth_deg
    return float(abs(azimuth_difference_deg(180.0 - a if mirrored else a, azimuth)))


def observe_cameras(
    tracks: dict[str, CameraTrack],
    model: AppearanceModel,
    *,
    config: EstimateConfig | None = None,
    cache: MatchCache | None = None,
    earlier: dict[str, float] | None = None,
) -> dict[str, CameraObservation]:
    """Steps 1-3 for each camera on its own: clean-up, registration, match, viewpoint, phase evidence.

    Cameras are independent until the HMM joins them (§6), so any subset of
    a window's cameras can be observed apart (in other processes) and the
    observations joined by :func:`decode_walk`; :func:`estimate_walk` is the
    two in one process. Tracks must have one length (not checked here).
    ``earlier`` (:func:`estimate_walk`) marks the cameras whose other side is
    observed too, for :func:`decode_walk` to weigh.
    """
    config = config or EstimateConfig()
    exemplars = model.exemplars() if config.method == "exemplars" else None
    if exemplars is not None and exemplars.n_phases != config.hmm.n_states:
        raise ValueError(f"exemplars have {exemplars.n_phases} phases, the HMM {config.hmm.n_states}")
    tracks, reports = _cleaned(tracks, model, config, cache)
    whole, whole_cache = model, cache
    out: dict[str, CameraObservation] = {}
    for name, track in tracks.items():
        model = _camera_model(whole, reports.get(name))
        cache = _camera_cache(whole_cache, model, whole)
        if exemplars is not None:
            exemplars = model.exemplars()
        T = len(track.silhouettes)
        labels = np.full(T, -1, np.int64)
        dist = np.full((T, model.n_clusters), np.inf, np.float32)
        cam_notes = []
        boxes = track.whole_boxes()  # heights, and the head's depth, of the whole body
        cue = _cue(track.silhouettes, boxes, reports.get(name)) if track.full_frame else None
        note = reports[name].note() if name in reports else None
        if note:
            cam_notes.append(note)
        if not track.full_frame:
            cam_notes.append(
                "cropped silhouettes: no position in the full frame, so no motion cue (ahead/behind decided by "
                "the majority of matches), and joints2d are in each crop's own pixels"
            )
        present, registered, d, keys = _matched(track, model, cache, whole)
        if present.size == 0:
            cam = CameraEstimate(_no_viewpoint(), cue, labels, np.full(T, np.nan), np.full((T, N_JOINTS, 2), np.nan),
                                 [*cam_notes, "no silhouette in this window"], reports.get(name))
            out[name] = CameraObservation(cam, track, dist, present)
            continue
        dist[present] = d
        labels[present] = np.argmin(d, axis=1)
        obs = np.full(T, np.nan)
        if exemplars is None:
            vp = estimate_viewpoint(*_cloud_paper(model, labels[present]), cue=cue,
                                    fall_min_elevation_deg=config.fall_min_elevation_deg)
            for k in present:
                sl = slice(model.member_offsets[labels[k]], model.member_offsets[labels[k] + 1])
                near = (_abs_az_diff(model.member_azimuth_deg[sl], vp.azimuth_deg) <= config.phase_view_window_deg) & (
                    np.abs(model.member_elevation_deg[sl] - vp.elevation_deg) <= config.phase_view_window_deg
                )
                obs[k] = _circular_mean(model.member_phase[sl][near] if near.any() else model.member_phase[sl])
            cam = CameraEstimate(vp, cue, labels, obs, np.full((T, N_JOINTS, 2), np.nan), cam_notes, reports.get(name))
            out[name] = CameraObservation(cam, track, dist, present)
            continue
        bits = pack(registered)
        vp, _ = _vote(_cloud_exemplars(model, exemplars, bits, d, config, cache, keys), len(bits), cue, config)
        evidence = _phase_evidence(exemplars, bits, vp, obs, present, config, cache, keys)
        cam = CameraEstimate(vp, cue, labels, obs, np.full((T, N_JOINTS, 2), np.nan), cam_notes, reports.get(name))
        mirror = None
        if _settles(config, cam, (earlier or {}).get(name)):  # its other side, for the other cameras' phase
            mirror_vp, mirror_obs = _mirrored(vp), np.full(T, np.nan)
            mirror = (mirror_vp, _phase_evidence(exemplars, bits, mirror_vp, mirror_obs, present, config, cache, keys),
                      mirror_obs)
        out[name] = CameraObservation(cam, track, dist, present, evidence, mirror, registered, bits, keys)
    return out


def refine_cameras(
    observations: dict[str, CameraObservation],
    states: np.ndarray,
    model: AppearanceModel,
    *,
    config: EstimateConfig | None = None,
    sides: dict[str, bool] | None = None,
    cache: MatchCache | None = None,
) -> dict[str, PhaseRefinement]:
    """Each observed camera's viewpoint voted again from the examples at the decoded phases.

    The phase is one for all cameras (they are synchronized) and the HMM
    decodes it from all of them over the window (§6); given it, a frame's
    silhouette is compared only with the examples of its phase, from every
    viewpoint, so a frame that looks like another phase seen from elsewhere
    (a cut limb, a hole) no longer votes for elsewhere. ``sides`` holds the
    cameras whose ahead/behind the other cameras settled. Per camera, like
    :func:`observe_cameras` (with the same ``cache``); observations without
    ``registered`` are skipped.
    """
    config = config or EstimateConfig()
    by_phase = _rows_by_phase(model.exemplars())  # the members' order is the cut models' too
    out = {}
    for name, o in observations.items():
        if o.registered is None or o.present.size == 0:
            continue
        c = o.estimate
        cam_model = _camera_model(model, c.cleanup)
        index, cam_cache = cam_model.exemplars(), _camera_cache(cache, cam_model, model)
        vp, weight = _vote(_cloud_at_phases(index, by_phase, o.registered, states[o.present], config, cam_cache,
                                            o.keys), len(o.present), c.cue, config, ahead=(sides or {}).get(name))
        obs = np.full(len(states), np.nan)
        ev = _phase_evidence(index, o.bits, vp, obs, o.present, config, cam_cache, o.keys)
        out[name] = PhaseRefinement(vp, obs, ev, int(np.sum(weight < 0.5)))
    return out


def estimate_walk(
    tracks: dict[str, CameraTrack],
    model: AppearanceModel,
    *,
    config: EstimateConfig | None = None,
    gait: GaitModel | None = None,
    cache: MatchCache | None = None,
    earlier: dict[str, float] | None = None,
) -> WalkEstimate:
    """Estimate phase per frame, 3D/2D joints and camera viewpoints for one window.

    :func:`observe_cameras`, then :func:`decode_walk` with
    :func:`refine_cameras`, all in this process.

    Parameters
    ----------
    tracks : dict of str to CameraTrack
        Synchronized cameras; every track has the same number of frames T.
    model : AppearanceModel
    config : EstimateConfig, optional
    gait : GaitModel, optional
        Defaults to the shipped CMU fit.
    cache : MatchCache, optional
        Registrations and matches of silhouettes seen before (overlapping live
        windows); the estimate is the same with or without (up to float32
        rounding, :mod:`estimator.matchcache`).
    earlier : dict of str to float, optional
        Each fixed camera's azimuth over the rig's earlier windows
        (:func:`estimator.windows.earlier_azimuths`): the side of the
        ahead/behind fold it keeps unless the other cameras' phase objects
        (``EstimateConfig.earlier_deg``; exemplar path only).

    Raises
    ------
    ValueError
        No cameras, tracks of different lengths, or no silhouette at all.
    """
    config = config or EstimateConfig()
    estimable_frames(tracks)
    observations = observe_cameras(tracks, model, config=config, cache=cache, earlier=earlier)
    return decode_walk(observations, config=config, gait=gait, model=model, earlier=earlier,
                       refine=lambda states, sides: refine_cameras(observations, states, model, config=config,
                                                                   sides=sides, cache=cache))


def prime_cache(tracks: dict[str, CameraTrack], model: AppearanceModel, cache: MatchCache, *,
                config: EstimateConfig | None = None, viewpoints: dict[str, Viewpoint] | None = None,
                states: np.ndarray | None = None) -> int:
    """Some frames of a window not yet closed, taken through what the window will ask of
    ``cache`` for them: then it is there when the window closes.

    Live windows are estimated when their last frame arrives; all but those
    frames can be looked at before. What depends on a silhouette alone is
    computed as the window will: the clean-up's scores, the registrations and
    eq. 8 matches, the members of the nearest clusters. What depends on the
    window's own choices is computed at a guess of them, the window before's:
    the examples near each camera's ``viewpoints`` (the phase evidence, §6)
    and those at the frames' ``states`` (the phase-given re-vote, see
    :func:`extrapolate_states`); a wrong guess costs the time it took, no
    more. The window's estimate is the same with or without. Returns the
    frames looked at.
    """
    config = config or EstimateConfig()
    if config.method != "exemplars":
        return 0
    index = model.exemplars()
    tracks, reports = _cleaned(tracks, model, config, cache, hidden=False)
    by_phase = _rows_by_phase(index) if states is not None else None
    looked = 0
    for name, track in tracks.items():
        if name in reports and reports[name].hidden_by:  # matched with a cut model, its share searched at the close
            continue
        present, registered, d, keys = _matched(track, model, cache)
        if not present.size:
            continue
        looked += present.size
        bits = pack(registered)
        _member_distances(model, index, bits, d, config.top_clusters, cache, keys)
        vp = (viewpoints or {}).get(name)
        if vp is not None and np.isfinite(vp.azimuth_deg):
            _phase_distances(index, bits, vp, cache, keys)
        if by_phase is not None:
            _cloud_at_phases(index, by_phase, registered, np.asarray(states)[present], config, cache, keys)
    return looked


def extrapolate_states(indices: np.ndarray, states: np.ndarray, n_states: int, ahead: np.ndarray) -> np.ndarray:
    """The HMM states of frames ``ahead`` from those decoded at ``indices``: the phase
    unwrapped and carried on at its rate over the window (least squares)."""
    angle = np.unwrap(2 * np.pi * np.asarray(states, float) / n_states)
    t = np.asarray(indices, float)
    slope, intercept = np.polyfit(t, angle, 1) if len(t) > 1 else (0.0, angle[0])
    return np.round((slope * np.asarray(ahead, float) + intercept) * n_states / (2 * np.pi)).astype(int) % n_states


def _log_hmm(hmm: PhaseHMM) -> tuple[np.ndarray, np.ndarray]:
    """The HMM's start and transition log-probabilities (log 0 = -inf)."""
    with np.errstate(divide="ignore"):
        return np.log(hmm.startprob_), np.log(hmm.transmat_)


def decode_walk(
    observations: dict[str, CameraObservation],
    *,
    config: EstimateConfig | None = None,
    gait: GaitModel | None = None,
    model: AppearanceModel | None = None,
    refine: Callable[[np.ndarray, dict[str, bool]], dict[str, PhaseRefinement]] | None = None,
    earlier: dict[str, float] | None = None,
) -> WalkEstimate:
    """Steps 4-6: the cameras joined: one phase path (§6), viewpoints again given it, joints.

    ``observations`` are every camera's (:func:`observe_cameras`, in any
    process; :meth:`CameraObservation.light` ones will do); ``refine`` maps the
    decoded states and settled sides to :func:`refine_cameras`'s result for
    every camera, wherever their registered silhouettes are (needed with
    ``config.phase_refine``). ``model`` is needed on the paper's path only.
    ``earlier`` is :func:`estimate_walk`'s, given to :func:`observe_cameras`
    too (which observes the other side of the cameras it may hold). The
    observations' estimates are updated in place.
    """
    config = config or EstimateConfig()
    gait = gait or load_gait()
    if not observations:
        raise ValueError("no cameras")
    T = len(next(iter(observations.values())).track.silhouettes)
    n_phases = config.hmm.n_states
    exemplars = config.method == "exemplars"
    if not exemplars and model is None:
        raise ValueError("the paper's path needs the model to decode")
    if exemplars:
        observations = _few_frames(observations, config.min_frames)
    cams = {name: o.estimate for name, o in observations.items()}
    if all(c.viewpoint.n_samples == 0 for c in cams.values()):
        raise ValueError("no non-empty silhouette in the window")
    log_start, log_trans = _log_hmm(config.hmm)
    sides: dict[str, bool] = {}
    held: set[str] = set()
    voted = {name: o for name, o in observations.items() if o.evidence is not None}  # exemplar path only
    if not exemplars:
        log_emission = config.hmm.log_emission(np.stack([c.observations for c in cams.values()], axis=1))
    else:
        if config.settle_ahead_behind:
            sides, held = _settle_ahead_behind(voted, log_start, log_trans, T, config, earlier or {})
        log_emission = np.zeros((T, n_phases))
        for o in voted.values():
            log_emission[o.present] -= o.evidence
    log_prob, states = viterbi(log_start, log_trans, log_emission)
    if voted and config.phase_refine:
        if refine is None:
            raise ValueError("phase_refine needs refine")
        refined = refine(states, sides)
        log_emission = np.zeros((T, n_phases))
        for name, o in observations.items():
            r = refined.get(name)
            if r is None or o.present.size == 0:  # set aside here, refined where it was observed
                continue
            c = o.estimate
            c.viewpoint, c.observations = r.viewpoint, r.observations
            log_emission[o.present] -= r.evidence
            if r.outliers:
                c.notes.append(f"viewpoint: {r.outliers} of {len(o.present)} frames count less (their match to "
                               "the model, or the viewpoint they point to, is an outlier of the window)")
        log_prob, states = viterbi(log_start, log_trans, log_emission)
    phase_posterior = posterior(log_start, log_trans, log_emission)
    for name in held:  # on the side its earlier windows found: said so (the window alone found the other)
        cams[name].viewpoint = replace(cams[name].viewpoint, flip="earlier")

    margin = 0.0
    if not exemplars and config.resolve_half_cycle:
        decoded = states
        states, margin = _resolve_half_cycle(model, states, cams, {n: o.distances for n, o in observations.items()},
                                             n_phases)
        if not np.array_equal(states, decoded):  # the path moved by half a cycle, its posterior with it
            phase_posterior = np.roll(phase_posterior, n_phases // 2, axis=1)

    phase = states / n_phases
    if exemplars:  # the paper's cluster means leave the half cycle to _resolve_half_cycle: offsets of 0.5 there
        _out_of_step(cams, phase, config.out_of_step)
    skeleton = forward_kinematics(gait.angles(phase), config.body)
    person = skeleton - skeleton[:, :N_JOINTS].mean(axis=1, keepdims=True)
    tracks = {name: o.track for name, o in observations.items()}
    for name, c in cams.items():
        if np.isfinite(c.viewpoint.azimuth_deg):
            if config.path_elevation:
                c.viewpoint = with_path_elevation(c.viewpoint, c.cue)
            placed = _place_joints(person, config.body, c.viewpoint, tracks[name].whole_boxes())
            c.joints2d = np.where(np.isfinite(tracks[name].boxes[:, :1, None]), placed, np.nan)
    return WalkEstimate(
        phase=phase,
        states=states,
        joints3d=person[:, :N_JOINTS],
        cameras=cams,
        log_prob=log_prob,
        half_cycle_margin=margin,
        notes=[] if exemplars else ["paper's path: cluster means only"],
        tracks=tracks,
        phase_posterior=phase_posterior,
        log_emission=log_emission,
    )


def _out_of_step(cams: dict[str, CameraEstimate], phase: np.ndarray, limit: float) -> None:
    """Each camera's :func:`phase_offset` from the decoded ``phase``, and a note on those over ``limit``
    where two or more cameras observed the phase (alone, a camera is the phase)."""
    for c in cams.values():
        c.phase_offset = phase_offset(c.observations, phase)
    if sum(c.phase_offset is not None for c in cams.values()) < 2:
        return
    for c in cams.values():
        if c.phase_offset is not None and c.phase_offset > limit:
            c.notes.append(f"out of step with the other cameras (its silhouettes match the walk {c.phase_offset:.2f} "
                           "cycles from the phase they agree on, in the median): its viewpoint in this window is "
                           "doubtful")


def _phase_evidence(index: ExemplarIndex, bits: np.ndarray, vp: Viewpoint, obs: np.ndarray, present: np.ndarray,
                    config: EstimateConfig, cache: MatchCache | None = None, keys: list[bytes] | None = None
                    ) -> np.ndarray:
    """Phase log-emission cost of one camera's frames at its viewpoint, (frames, n_phases);
    the nearest phase is written into ``obs``."""
    pd = _phase_distances(index, bits, vp, cache, keys)
    obs[present] = np.argmin(pd, axis=1) / index.n_phases
    return (pd - pd.min(axis=1, keepdims=True)) / config.tau_phase


def _mirrored(vp: Viewpoint) -> Viewpoint:
    """The viewpoint on the other side of the ahead/behind fold (azimuth ``180 - a``)."""
    return replace(vp, azimuth_deg=(180.0 - vp.azimuth_deg) % 360.0, flip="cameras")


def _contested(camera: CameraEstimate) -> bool:
    """Whether a camera's ahead/behind rests on no motion cue, or on a head path the height contradicted.

    The height alone is trusted on a conflict (a walker who changes speed
    bends the head's path); the head alone is not, when the feet were cut (the
    cut heights were dropped, and the head may be the one misled). Behind an
    edge fixed in the image across most of the window the head's width and
    path are all there is (the heights are not the walker's size), and they
    stand, the width as the height does on a conflict: the other cameras'
    phase, all of them behind walls, turned 7 of 37 right cameras of seed
    23's CMU walks to the wrong side when asked of the head's path alone. A cue too
    weak to decide is not contested: the window may hold a turn, where the
    cameras' phases agree best on a side that is right for half of it
    (measured: phase within 1/20 on 0.5 of the frames against 0.9).
    """
    cue = camera.cue
    return cue is None or (cue.conflict and cue.source == "head")


def _settle_ahead_behind(observations: dict[str, CameraObservation], log_start: np.ndarray, log_trans: np.ndarray,
                         T: int, config: EstimateConfig, earlier: dict[str, float]
                         ) -> tuple[dict[str, bool], set[str]]:
    """Ahead/behind of the cameras whose motion cue is contested, absent or short, from the other cameras' phase,
    and of those whose ``earlier`` windows found them on the other side.

    Seen from azimuth ``a`` or ``180 - a`` (in front of the walker or behind),
    a silhouette looks alike at phases half a cycle apart, so a camera on the
    wrong side of the fold sees the phase shifted by half a cycle. The cameras
    are synchronized and share one phase (§6): of the assignments of sides to
    the open cameras (a shadow cut at the feet makes the height and the
    head disagree on whether the walker approaches; cropped input has no
    cue), the one whose summed phase evidence the HMM decodes most probably is
    kept, if it beats the default by ``config.settle_margin`` per frame (each
    camera's other side was observed as its ``mirror``). The default is the
    cues' choice, and for a camera that a fixed rig's earlier windows found on
    the other side of the fold (:func:`_against_earlier`), that side: a window
    of 20 frames is less sure of it than the windows before (on the live
    composite walks, about half of a window's errors over 30 deg were such
    folds, docs/ROBUSTNESS.md, "The side the earlier windows found"). Each
    camera's ``evidence`` and viewpoint are updated in place. Returns the
    side (True: ahead) of every camera whose side was settled so, for the
    later re-votes, and the cameras held on their earlier side.
    """
    names = [n for n, o in observations.items() if np.isfinite(o.estimate.viewpoint.azimuth_deg)]
    against = {n for n in names if _against_earlier(config, observations[n].estimate, earlier.get(n))}
    if not any(_witness(config, observations[m].estimate, earlier.get(m)) for m in names if m not in against):
        against = set()  # no camera tells that the walker did not turn (or the rig move)

    def is_open(n: str, with_earlier: bool = True) -> bool:  # a cue on few frames yields only to one that saw more
        o = observations[n]
        return o.mirror is not None and (_contested(o.estimate) or with_earlier and n in against
                                         or _few(config, o.estimate)
                                         and any(observations[m].present.size >= config.settle_few_frames
                                                 for m in names if m != n))

    # 2^8 decodes at most; the cameras the earlier windows hold first
    contested = sorted((n for n in names if is_open(n)), key=lambda n: n not in against)[:8]
    if len(names) < 2 or not contested:
        return {}, set()
    other = np.zeros((T, len(log_start)))
    for n in names:
        if n not in contested:
            other[observations[n].present] -= observations[n].evidence
    lps = {}  # the HMM's log-probability of each assignment of sides to the open cameras (1: the other side)
    for choice in np.ndindex(*(2,) * len(contested)):
        total = other.copy()
        for n, flip in zip(contested, choice):
            o = observations[n]
            total[o.present] -= o.mirror[1] if flip else o.evidence
        lps[choice] = viterbi(log_start, log_trans, total)[0]

    def decided(choices: list[tuple], start: tuple) -> tuple[tuple, float]:
        """The most probable of ``choices`` if it beats ``start`` by the margin, and by how much."""
        best = max(choices, key=lps.get)
        gain = lps[best] - lps[start]
        return (best, gain) if best != start and gain > config.settle_margin * T else (start, 0.0)

    shut = [not is_open(n, with_earlier=False) for n in contested]  # open only because of the earlier windows
    chosen, gain = decided(list(lps), tuple(int(n in against) for n in contested))
    alone, alone_gain = decided([c for c in lps if not any(f and s for f, s in zip(c, shut))],
                                (0,) * len(contested))  # the window's own choice
    sides, held = {}, set()
    for n, flip, own in zip(contested, chosen, alone):
        if not flip:
            continue
        o = observations[n]
        c = o.estimate
        c.viewpoint, o.evidence, c.observations = o.mirror
        sides[n] = bool(np.cos(np.deg2rad(c.viewpoint.azimuth_deg)) >= 0)
        if n in against and not own:  # the earlier windows decided it: alone, the window keeps the other side
            held.add(n)
            c.notes.append(f"ahead/behind: on the side this camera's earlier windows found ({earlier[n] % 360:.0f} "
                           "deg), where this window alone found the other; the other cameras' phase does not object")
            continue
        why = ("was absent" if c.cue is None else "was contested" if _contested(c)
               else f"was measured on {c.cue.n_frames} frames only" if _few(config, c) else "said the other side")
        c.notes.append(f"ahead/behind settled by the other cameras' phase (the motion cue {why}; "
                       f"log-probability {alone_gain if own else gain:.1f} better over {T} frames)")
    return sides, held


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
