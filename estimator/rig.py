"""The rig and the person's posture from the measured 2D postures (Wang–Leow §4 after §3).

Izo–Grimson gives each camera's viewpoint relative to the walker, and so a
rig: ``R_c R_0^T`` from the viewpoints (:func:`viewpoint_rotations`), a few
degrees off per camera. The mNBP postures measured on each silhouette
(:mod:`estimator.mnbp`) are 2D joint tracks of *this* walker, which Wang–Leow
§4 turns into the rig and the 3D posture (:func:`estimator.selfcal.self_calibrate`,
the refined path: bundle adjustment with the upright prior). The adjustment is
started twice, from the closed form and from the viewpoints' rig, and keeps
the lower cost; each camera's rotation is then fused with the viewpoints'
by their errors, and pinhole cameras are adjusted from there
(:mod:`estimator.perspective`: rotation, centre and focal length per camera),
which the scaled-orthographic model cannot give and which halves the tail of
the rotation errors (docs/POSTURE.md). When self-calibration cannot run or
fails, the viewpoints' rig stands and ``notes`` say why. The 3D joints come out in camera 0's
frame; :func:`person_frame` turns them to the walker's (x walking direction,
y left, z up) by the mean hip line and trunk, and they are scaled to metres
so that the chain ankle-knee-hip-shoulder-head has the length it has on the
model's body at the given stature (:class:`RigConfig`).
"""

from __future__ import annotations

import itertools
import warnings
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial.transform import Rotation

from .camera import aimed_rotation, world_to_camera_rotation
from .epipolar import refine_from_starts
from .frontier import FrontierConfig, outlines, refine_on_tangents
from .gait import load_gait
from ._selfcal_core import geodesic_deg
from .joints import JOINT_INDEX, N_JOINTS
from .mnbp import MNBPConfig, measure_postures, person_widths, posture_sequences
from .mnbp3d import MNBP3DConfig, posture_sequence3d
from .pipeline import CameraTrack, WalkEstimate, concat_estimates, take_frames
from .perspective import KEYPOINT_SETTINGS, PerspectiveConfig, PerspectiveRig, perspective_refine
from .pinhole import project, triangulate
from .selfcal import RIGID_LINKS, input_warnings, named_note, self_calibrate
from .skeleton import BodyShape, forward_kinematics

__all__ = ["Rig", "RigAccumulator", "RigConfig", "SEGMENTS", "aligned_error", "attach_rig", "calibrate_rig",
           "keypoint_frames", "person_frame", "rotations_from_viewpoints", "segment_lengths", "similarity_aligned",
           "smoothed", "stature_scale", "viewpoint_rotations"]

_J = JOINT_INDEX
SEGMENTS: dict[str, tuple[tuple[int, ...], tuple[int, ...]]] = {
    "left_shank": ((_J["left_knee"],), (_J["left_ankle"],)),
    "right_shank": ((_J["right_knee"],), (_J["right_ankle"],)),
    "left_thigh": ((_J["left_hip"],), (_J["left_knee"],)),
    "right_thigh": ((_J["right_hip"],), (_J["right_knee"],)),
    "left_upper_arm": ((_J["left_shoulder"],), (_J["left_elbow"],)),
    "right_upper_arm": ((_J["right_shoulder"],), (_J["right_elbow"],)),
    "left_forearm": ((_J["left_elbow"],), (_J["left_wrist"],)),
    "right_forearm": ((_J["right_elbow"],), (_J["right_wrist"],)),
    "hip_width": ((_J["left_hip"],), (_J["right_hip"],)),
    "shoulder_width": ((_J["left_shoulder"],), (_J["right_shoulder"],)),
    "trunk": ((_J["left_hip"], _J["right_hip"]), (_J["left_shoulder"], _J["right_shoulder"])),
    "neck_head": ((_J["left_shoulder"], _J["right_shoulder"]), (_J["head"],)),
}
"""Segments between the 13 joints: (joints averaged at one end, at the other)."""



@dataclass(frozen=True)
class RigConfig:
    """How the rig and the person's posture are computed.

    Attributes
    ----------
    height_m : float
        The walker's stature: the 3D posture and the segment lengths are in
        metres at this stature (silhouettes carry no absolute scale).
    upright : bool
        The bundle adjustment's upright prior (:func:`estimator.selfcal.self_calibrate`).
    min_frames : int
        Fewer frames seen by at least two cameras: the viewpoints' rig stands.
    perspective : bool
        Finish with pinhole cameras (:func:`estimator.perspective.perspective_refine`:
        rotation, centre and focal length per camera; needs full-frame
        tracks): the camera rotations, focal lengths and centres (metres, in
        the reference camera's frame) then come from it.
    pinhole : PerspectiveConfig
    pinhole_viewpoint_weight : float
        The viewpoints' rig as a prior of the pinhole adjustment: a camera's
        turn away from it costs as much as this share of the walker's image
        height of reprojection error per degree (0: no prior). The mNBP
        postures' errors are systematic (the torso is the model's, the
        capsules are not the person's body), and the adjustment followed
        them: with it exact, the pinhole minimum left 3 of 24 tuning walks
        more than 2 deg worse than the viewpoints' rig at their worst pair.
        0.01 was chosen on the tuning walks (seed 11: 0.003, 0.01, 0.02),
        docs/POSTURE.md.
    pinhole_max_rms : float
        The pinhole result is refused (the scaled-orthographic rig stands, with
        a note) when its reprojection error exceeds this fraction of the
        walker's image height.
    pinhole_epipolar_start : bool
        Also start the pinhole adjustment from the epipolar geometry of the
        best-seen camera pair (:func:`estimator.epipolar.refine_from_starts`,
        as ``posecal selfcal`` does) and keep the start that reprojects
        better; only without a viewpoint prior (``pinhole_viewpoint_weight``
        0: a detector's keypoints, :meth:`for_keypoints`) and with three
        cameras or more. Two views keep the twofold ambiguity of their
        relative pose, and under a detector's noise the wrong basin can
        reproject as well: there the start fused with the viewpoints
        decides (on 24 walks with 2-3 % noise, 2 of 9 two-camera walks
        went 0.7-4 -> 22-27 deg with it; one 3-camera walk 35 -> 2.7).
    pinhole_viewpoint_start : bool
        With the viewpoints' prior, also start the pinhole adjustment from the
        viewpoints' rig, not only from the rotations fused with it, and keep
        the end of lower cost. The adjustment can stop on a slope short of
        the minimum in the direction two views hardly see: on the composite
        videos (docs/ROBUSTNESS.md, "Two starts of the pinhole adjustment")
        it took seed 7's two-camera walk 5 from 16.7 to 5.8 deg, seed 5's
        walk 2 from 8.8 to 3.7.
    pinhole_depth_starts : tuple of str
        Where each rotation start places the walker
        (:attr:`estimator.perspective.PerspectiveConfig.depth_start`):
        ``"fixed"``, at one depth from camera 0 in every frame with the focal
        lengths at their prior; ``"frames"``, at the depth its image size
        gives in each frame, with the focal lengths this tells. Each is tried
        and the end of lowest cost kept. A walker who nears and recedes
        (the live benchmark's walk across 100 deg of views, focal lengths
        0.37 image widths) leaves the first start 7-34 deg off where the
        second ends 3-7 deg off; on the composite videos the two end the same
        on 20 of 24 walks (docs/POSTURE.md, "A walker who nears and
        recedes").
    pinhole_focal_widths : (float, float)
        ... or when a focal length lies outside this many image widths (a far
        camera's focal length is loosely determined, 10-20 widths for a true
        2.4 are seen with good rotations; a diverged fit gives 100s).
    max_frames : int
        Frames the rig is calibrated on, evenly spread over the segment (the
        adjustments grow with the frames: 22 s for 200 frames); the person's
        posture is given on those frames.
    start_frames : int
        With ``perspective``, the scaled-orthographic adjustment (the
        pinhole adjustment's start and its fusion with the viewpoints) runs
        on at most this many of those frames, the middle ones; the pinhole
        adjustment on all. Its cost grows faster than the frames (the
        temporal prior's dense solve): on a 2-camera x 60-frame walk the rig
        took 3.84 s with all 60 and 0.85 s with 30, the rotations the same to
        0.01 deg.
    viewpoint_sigma_deg : float
        Typical error of a camera's rotation from the viewpoints' rig
        (``bench/eval_rig_from_silhouettes.py``: median 6-7.6 deg per camera
        pair). Each camera's self-calibrated rotation is fused with it, weighted
        by the inverse squares of this and of the self-calibration's posterior
        error; 0 keeps the self-calibration alone. With ``perspective`` the
        fused rotations are where the pinhole adjustment starts.
    rounds : int
        Rounds of Wang–Leow's loop (§5), counting the first (2D mNBP per
        camera, then self-calibration): each further round is 3D mNBP over
        all views with the pinhole cameras (:mod:`estimator.mnbp3d`), a short
        2D correction per view (``polish``) and the pinhole adjustment again
        (:func:`iterate_rounds`). Default 1: on the evaluation walks a second
        round has not improved the rig or the posture yet (docs/POSTURE.md).
    round3d : MNBP3DConfig
    polish : MNBPConfig or None
    converged_deg : float
        Stop the rounds when no camera turns more than this.
    hidden_view_doubt : float
        A camera whose walker is hidden below on half of the frames or more (a
        wall in front: :attr:`estimator.pipeline.CameraTrack.hidden`) has a
        viewpoint this many times less sure: the shape that tells the
        elevation is mostly the legs', and behind walls the elevations come
        out pulled towards the middle of the grid (seed 23's walled CMU walks:
        cameras 24-34 deg above the walker 6-24 deg too low).
        Its ``viewpoint_sigma_deg`` is multiplied by it and its weight in the
        pinhole adjustment's viewpoint prior divided by it (a camera pair's by
        the root mean square of its two cameras'). There, 2 took the rig from
        7.46 / 28.32 to 6.54 / 24.56 deg (median / p90, ``fixed_wall``) and
        from 7.17 / 30.88 to 5.93 / 32.76 (``low_wall``; 3: 6.57 / 32.57).
        1: all alike.
    max_disagreement_deg : float
        A self-calibrated rig with a camera further than this from the viewpoints' rig is taken as
        a wrong solution (a depth flip, a diverged fit: seen 134 deg off on 18 live frames) and the
        viewpoints' rig stands, with a note. On the evaluation walks both are right within 13 deg
        (CMU) and 20 deg (stylised) at worst, so they disagree by at most 25-33 deg there. 0: off.
    consecutive : bool
        The estimate's frames are consecutive frames of one recording (false for frames gathered
        from many windows, :class:`RigAccumulator`): only then does the self-calibration use that
        the tracks are a smooth motion (its temporal prior, and the pinhole adjustment's
        ``pinhole.smooth``), and only on frames it takes in a row.
    tangents : FrontierConfig or None
        With pinhole cameras, adjust them to the silhouettes' epipolar
        tangents (:func:`estimator.frontier.refine_on_tangents`), a
        constraint the body model does not enter, then fit the posture again
        to the 2D postures with those cameras held (focal lengths fixed,
        rotations under a prior of ``tangent_hold`` walker heights per
        degree). Kept when the tangent residual falls and no camera turns
        more than ``tangent_max_turn_deg``; rotation directions the tangents
        hardly see are held where the pinhole rig put them
        (``FrontierConfig.hold_std_deg``). Measured on the tuning walks
        (seed 11): camera-pair rotations 2.16 / 6.08 deg -> 0.40 / 2.62
        (median / p90); held-out seed 23: 3.89 / 7.97 -> 0.63 / 4.75 (CMU
        walks), 5.62 / 8.63 -> 0.69 / 2.61 (stylised gait); seed 31: 0.44 /
        2.27 and 0.52 / 3.42; with holes and cut limbs (seed 23): 6.64 /
        15.72 -> 2.15 / 13.57 (docs/POSTURE.md). None: off.
    tangent_hold : float
    tangent_max_turn_deg : float
    tangent_max_residual_px : float
        ... and when the tangents' median residual at the end is at most
        this: on clean and shadowed tuning walks the refinements ended at
        0.11-0.33 px; an outline the body does not make (a limb cut off the
        silhouette) leaves more (0.53 px on a walk of seed 23 that the
        tangents took 3.7 deg further off).
    posture_weight_below : float or None
        In the pinhole adjustment (and the posture's refit on the tangents'
        cameras), a camera-frame whose mNBP posture explains its silhouette
        with a score under this (:attr:`estimator.mnbp.Posture2D.score`: the
        drawn body's agreement with the silhouette, 1 = exact) weighs 0.05
        instead of 1: such silhouettes hold a ghost, a passer-by or a lost
        limb, and so do their postures (on the composite videos of
        ``bench/eval_composite.py``, seed 5: 2D error 0.077 of the walker's
        height in median under 0.3, 0.023 over 0.5). Nearly, not wholly, left
        out: a frame every camera saw badly still has its posture. None: off.
    hidden_weight : float
        The weight there of a joint mNBP placed below a silhouette whose lowest
        part is hidden (a wall in front, the frame's bottom edge:
        :func:`hidden_joints`): placed by the articulation, not measured, but
        the only evidence of a shin that no camera sees. On the CMU walks of
        ``bench/eval_rig_from_silhouettes.py --seed 23 --damage low_wall``:
        0.05 took the 3D posture from 0.031 to 0.042 of the stature (the
        ankles 0.040 -> 0.071) for the same rotations; 0.3 keeps it at 0.031.
        (Left out of the scaled-orthographic start as well, they gave the same
        rotations and 3D posture within noise, and a walk whose pinhole
        cameras were refused had no legs.)
    smooth_posture : bool
        With pinhole cameras and ``consecutive`` frames, the adjusted 3D posture is filtered
        ``[1, 2, 1] / 4`` over each frame and its two neighbours (where both are frames of the
        adjustment one frame apart) before it is reported and projected (:func:`attach_rig`):
        the adjustment fits each frame alone, and at 15 Hz a joint's frame-to-frame noise is
        larger than its motion's curvature. Measured on 12 held-out walks (``bench/eval_mnbp.py``'s
        seed 8): 2D error / height 0.0212 / 0.0453 -> 0.0206 / 0.0432 (CMU), 0.0207 / 0.0452 ->
        0.0203 / 0.0433 (stylised), median / p90. The rotations are the adjustment's either way.
    """

    height_m: float = 1.75
    upright: bool = True
    min_frames: int = 8
    viewpoint_sigma_deg: float = 7.0
    perspective: bool = True
    pinhole: PerspectiveConfig = PerspectiveConfig()
    pinhole_max_rms: float = 0.04
    pinhole_viewpoint_weight: float = 0.01
    pinhole_epipolar_start: bool = False
    pinhole_viewpoint_start: bool = True
    pinhole_depth_starts: tuple[str, ...] = ("fixed", "frames")
    pinhole_focal_widths: tuple[float, float] = (0.3, 50.0)
    max_frames: int = 60
    start_frames: int = 30
    rounds: int = 1
    round3d: MNBP3DConfig = MNBP3DConfig()
    polish: MNBPConfig | None = MNBPConfig(n_iterations=3, joint_sigma=(0.03, 0.015), step_position=(0.01, 0.005),
                                           step_angle_deg=(8.0, 3.0), step_length=(0.05, 0.02), explore=0.0,
                                           prior_sigma=0.05)
    converged_deg: float = 0.2
    consecutive: bool = True
    hidden_view_doubt: float = 2.0
    max_disagreement_deg: float = 45.0
    smooth_posture: bool = True
    tangents: FrontierConfig | None = FrontierConfig()
    tangent_hold: float = 1.0
    tangent_max_turn_deg: float = 20.0
    tangent_max_residual_px: float = 0.4
    posture_weight_below: float | None = 0.3
    hidden_weight: float = 0.3

    def __post_init__(self) -> None:
        if not (np.isfinite(self.height_m) and 0.5 <= self.height_m <= 2.5):
            raise ValueError(f"height_m must be a stature in metres (0.5-2.5), got {self.height_m!r}")
        if not 1 <= self.rounds <= 5:
            raise ValueError(f"rounds must be 1 to 5, got {self.rounds!r}")

    @classmethod
    def for_keypoints(cls, **kwargs) -> RigConfig:
        """The settings for a detector's 2D keypoints in place of the mNBP postures
        (:func:`calibrate_rig`'s ``keypoints``): rounds of Cauchy reweighting in the pinhole
        adjustment (:data:`estimator.perspective.KEYPOINT_REWEIGHT`, as ``posecal selfcal``), no pull
        towards the viewpoints' rig (its prior is for the mNBP postures' systematic errors, which
        keypoints do not share), no 3D mNBP rounds and no epipolar tangents (both correct the mNBP
        postures); measured on a test walk: 0.20 / 0.51 deg, with the tangents 1.99 / 1.47, with the
        silhouettes' settings 1.26 / 1.16 (docs/POSTURE.md). The upright walker's priors where the
        perspective is weak, the walker's smooth motion (:data:`estimator.perspective.KEYPOINT_SMOOTH`,
        over consecutive frames) and the epipolar start with three cameras or more, as ``posecal selfcal``
        (:attr:`pinhole_epipolar_start`), and no cross-check against the viewpoints' rig: keypoints
        calibrate better than the viewpoints tell, and a camera that sees the walker across a wide
        angle of view has viewpoints 50-70 deg from its rotation (``bench/bench_service_live.py``,
        whose 300-frame walk crosses 100 deg views), where the check refused right rigs."""
        return cls(**{**cls().keypoint_settings(), **kwargs})

    def keypoint_settings(self) -> dict:
        """The fields :meth:`for_keypoints` sets, to apply to another configuration with ``replace``."""
        return {"pinhole": replace(self.pinhole, **KEYPOINT_SETTINGS),
                "pinhole_viewpoint_weight": 0.0, "pinhole_epipolar_start": True, "max_disagreement_deg": 0.0,
                "rounds": 1, "tangents": None}


@dataclass
class Rig:
    """Camera rotations relative to the reference camera, and the person's posture and body.

    Attributes
    ----------
    cameras : tuple of str
        Camera names.
    rotations : ndarray of shape (C, 3, 3)
        ``R_c R_ref^T``, rows image u, image v, viewing direction (the
        convention of ``posecal selfcal``).
    scales : ndarray of shape (C,)
        Image scale of each camera relative to the reference (scaled orthographic).
    source : str
        ``"self-calibration"`` or ``"viewpoints"`` (the fallback).
    euler_std_deg, scale_std : ndarray or None
        Posterior standard deviations from the scaled-orthographic bundle
        adjustment (Laplace); None with pinhole cameras (not computed there).
    rotvec_cov : ndarray of shape (C, 3, 3) or None
        The same posterior as each rotation error's rotation-vector covariance,
        radians squared (:attr:`estimator.selfcal.SelfCalibration.rotvec_cov`);
        None where ``euler_std_deg`` is.
    joints3d : ndarray of shape (T, 13, 3) or None
        The person's posture in the person frame, metres, centred on the 13
        joints' centroid per frame; NaN where seen by fewer than two cameras.
        None when the rig is the viewpoints'.
    segments_m : dict of str to float
        Median segment lengths (:data:`SEGMENTS`), metres; empty without joints3d.
    height_m : float
    notes : list of str
    reference : str
        The camera the rotations are relative to (the first camera in the rig).
    focal_px, centres_m, walker_m : ndarray or None
        With pinhole cameras: focal lengths (C,), camera centres (C, 3) and the
        walker's mean position (3,), metres in camera 0's frame (x right, y
        down, z forward).
    image_sizes : ndarray of shape (C, 2) or None
        With pinhole cameras: each camera's image (width, height) in pixels,
        whose centre is the principal point.
    joints2d : ndarray of shape (C, T, 13, 2) or None
        With pinhole cameras: the adjusted 3D posture projected into each
        camera (pixels of the full frame), on the frames the adjustment used;
        NaN elsewhere. Every view's postures shaped it, so it is nearer the
        truth than one view's mNBP alone (:func:`attach_rig` reports it).
    tangents : dict or None
        With pinhole cameras and ``RigConfig.tangents``: what the refinement on
        the epipolar tangents found (:func:`estimator.frontier.refine_on_tangents`):
        ``used``, ``frame_pairs``, ``residual_px`` (median before and after; after None when no
        outline pair was left to measure), ``largest_turn_deg``, ``rotation_std_deg`` (None where it
        did not run or could not be measured), ``held_directions``.
    """

    cameras: tuple[str, ...]
    rotations: np.ndarray
    scales: np.ndarray
    source: str
    euler_std_deg: np.ndarray | None = None
    scale_std: np.ndarray | None = None
    joints3d: np.ndarray | None = None
    segments_m: dict[str, float] = field(default_factory=dict)
    height_m: float = 1.75
    notes: list[str] = field(default_factory=list)
    focal_px: np.ndarray | None = None
    centres_m: np.ndarray | None = None
    walker_m: np.ndarray | None = None  # the walker's mean position in camera 0's frame (pinhole rig)
    reference: str | None = None  # default: cameras[0]
    rotvec_cov: np.ndarray | None = None
    image_sizes: np.ndarray | None = None
    joints2d: np.ndarray | None = None
    tangents: dict | None = None

    def __post_init__(self) -> None:
        self.reference = self.reference or self.cameras[0]

    def to_dict(self) -> dict:
        """The result's ``rig`` (strict JSON: a camera left out of the rig has ``None`` values)."""
        cams = {}
        for k, name in enumerate(self.cameras):
            r = self.rotations[k]
            ok = bool(np.all(np.isfinite(r)))
            d = {"rotation": _num(r, 6),
                 "rotvec": _num(Rotation.from_matrix(r).as_rotvec(), 6) if ok else None,
                 "quaternion_xyzw": _num(Rotation.from_matrix(r).as_quat(canonical=True), 8) if ok else None,
                 "euler_xyz_deg": _num(Rotation.from_matrix(r).as_euler("xyz", degrees=True), 3) if ok else None,
                 "scale": _num(self.scales[k], 5)}
            if self.euler_std_deg is not None:
                d["euler_xyz_std_deg"] = _num(self.euler_std_deg[k], 3)
            if self.rotvec_cov is not None:
                d["rotvec_covariance_rad2"] = _num(self.rotvec_cov[k], 9)
            if self.scale_std is not None:
                d["scale_std"] = _num(self.scale_std[k], 5)
            if self.focal_px is not None:
                d["focal_px"] = _num(self.focal_px[k], 1)
                d["centre_m"] = _num(self.centres_m[k], 3)
            if self.image_sizes is not None and np.all(np.isfinite(self.image_sizes[k])):
                d["image_size"] = [int(v) for v in self.image_sizes[k]]
            cams[name] = d
        out = {"reference": self.reference, "source": self.source, "cameras": cams}
        if self.tangents is not None:
            out["epipolar_tangents"] = self.tangents
        return out

    def body_dict(self) -> dict | None:
        """The result's ``body``: segment lengths in metres and relative to stature; None without them."""
        if not self.segments_m:
            return None
        return {"stature_m": self.height_m,
                "segments": {k: {"metres": round(v, 4), "relative": round(v / self.height_m, 4)}
                             for k, v in self.segments_m.items()}}


def rotations_from_viewpoints(viewpoints: list[tuple[float, float]]) -> np.ndarray:
    """``R_c R_0^T`` (C, 3, 3) of cameras seen from (azimuth, elevation) in degrees, relative
    to the first; NaN for a camera whose viewpoint is not finite."""
    rots = np.stack([world_to_camera_rotation(az, el) if np.isfinite(az) and np.isfinite(el)
                     else np.full((3, 3), np.nan) for az, el in viewpoints])
    return rots @ rots[0].T


def viewpoint_rotations(estimate: WalkEstimate, focal_widths: float | None = None) -> np.ndarray:
    """``R_c R_0^T`` (C, 3, 3) from each camera's Izo–Grimson viewpoint; NaN for a camera without one.

    A viewpoint is the walker's, not the camera's axis. By default (None), or
    for crops, each camera looks straight at the walker. With
    ``focal_widths`` and full-frame silhouettes each camera is aimed so that
    it sees the walker where its silhouettes are (their boxes' mean centre,
    the principal point at the image centre, a focal length of that many
    image widths; :func:`estimator.camera.aimed_rotation`). Not the default:
    aimed at one image width, 20-frame windows of walks 4-15 m away went 8.36 /
    17.7 -> 8.11 / 13.2 deg (median / p90; 6.42 / 12.2 with the true focal
    lengths), but whole walks and the rig built on them did not change beyond
    their noise (docs/POSTURE.md, "The viewpoints' rig, aimed").
    """
    views = [(c.viewpoint.azimuth_deg, c.viewpoint.elevation_deg) for c in estimate.cameras.values()]
    if focal_widths is None:
        return rotations_from_viewpoints(views)
    tracks = estimate.tracks or {}
    rots = []
    for name, (az, el) in zip(estimate.cameras, views):
        t = tracks.get(name)
        seen = None if t is None or not t.full_frame or t.image_size is None else np.isfinite(t.boxes).all(axis=1)
        if not (np.isfinite(az) and np.isfinite(el)):
            rots.append(np.full((3, 3), np.nan))
        elif seen is None or not seen.any():
            rots.append(world_to_camera_rotation(az, el))
        else:
            centre = np.mean(t.boxes[seen, :2] + t.boxes[seen, 2:] / 2, axis=0)
            size = np.asarray(t.image_size, float)
            rots.append(aimed_rotation(az, el, centre - size / 2, focal_widths * size[0]))
    rots = np.stack(rots)
    return rots @ rots[0].T


def segment_lengths(joints3d: np.ndarray) -> dict[str, np.ndarray]:
    """Length of every :data:`SEGMENTS` entry per frame: name -> (T,)."""
    out = {}
    for name, (a, b) in SEGMENTS.items():
        pa, pb = joints3d[:, list(a)].mean(axis=1), joints3d[:, list(b)].mean(axis=1)
        out[name] = np.linalg.norm(pa - pb, axis=-1)
    return out


def similarity_aligned(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """``est`` (T, J, 3) moved per frame by the similarity transform (Procrustes with scale) that
    takes its finite joints nearest ``true``'s; NaN frames where fewer than 4 joints are finite in
    both. For evaluations and figures: the posture's shape, whatever its frame and size."""
    est, true = np.asarray(est, float), np.asarray(true, float)
    out = np.full(est.shape, np.nan)
    for t, (a, b) in enumerate(zip(est, true)):
        ok = np.isfinite(a).all(axis=1) & np.isfinite(b).all(axis=1)
        if ok.sum() < 4:
            continue
        ca, cb = a[ok].mean(0), b[ok].mean(0)
        a0, b0 = a[ok] - ca, b[ok] - cb
        u, sv, vt = np.linalg.svd(a0.T @ b0)
        d = np.sign(np.linalg.det(u @ vt))
        r = u @ np.diag([1.0, 1.0, d]) @ vt
        scale = (sv * [1.0, 1.0, d]).sum() / (a0 ** 2).sum()
        out[t] = scale * (a - ca) @ r + cb
    return out


def aligned_error(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per frame: mean joint distance of ``est`` (T, J, 3) to ``true`` after
    :func:`similarity_aligned`, over the joints finite in both; NaN where fewer than 4 are."""
    d = np.linalg.norm(similarity_aligned(est, true) - np.asarray(true, float), axis=-1)  # (T, J)
    ok = np.isfinite(d)
    return np.where(ok.any(axis=1), np.where(ok, d, 0.0).sum(axis=1) / np.maximum(ok.sum(axis=1), 1), np.nan)


def stature_scale(joints3d: np.ndarray, height_m: float) -> float:
    """Metres per unit of ``joints3d`` (T, 13, 3) for a walker of stature ``height_m``: the
    chain ankle-knee-hip-shoulder-head as long as on the model's body of that stature (NaN
    when the joints give it no length)."""
    return _scale_for(_median_lengths(joints3d), height_m)


def _median_lengths(joints3d: np.ndarray) -> dict[str, float]:
    """Each :data:`SEGMENTS` entry's median length over the frames."""
    return {k: float(np.nanmedian(v)) for k, v in segment_lengths(joints3d).items()}


def _scale_for(lengths: dict[str, float], height_m: float) -> float:
    """:func:`stature_scale` of median segment ``lengths``."""
    chain = _stature_chain(lengths)
    return _stature_chain(_model_lengths(height_m)) / chain if np.isfinite(chain) and chain > 0 else float("nan")


def _stature_chain(lengths: dict[str, float]) -> float:
    """Ankle to head: mean of left and right leg segments, then trunk and neck-head."""
    def side(k: str) -> float:
        return float(np.nanmean([lengths.get(f"left_{k}", np.nan), lengths.get(f"right_{k}", np.nan)]))

    return side("shank") + side("thigh") + lengths["trunk"] + lengths["neck_head"]


def _model_lengths(height_m: float) -> dict[str, float]:
    """The model body's segment lengths at ``height_m`` (the shipped gait at phase 0)."""
    joints = forward_kinematics(load_gait().angles(np.zeros(1)), BodyShape(height=height_m))[:, :N_JOINTS]
    return {k: float(v[0]) for k, v in segment_lengths(joints).items()}


def person_frame(joints3d: np.ndarray) -> np.ndarray:
    """Joints (T, 13, 3) in any right-handed frame turned to the walker's: z along the mean
    trunk (hips to shoulders), y along the mean hip line (right to left) made
    perpendicular to it, x = y cross z (walking direction); centred per frame."""
    j = np.asarray(joints3d, float)
    hips = j[:, [_J["left_hip"], _J["right_hip"]]]
    shoulders = j[:, [_J["left_shoulder"], _J["right_shoulder"]]]
    up = np.nanmean(shoulders.mean(axis=1) - hips.mean(axis=1), axis=0)
    up /= np.linalg.norm(up)
    left = np.nanmean(hips[:, 0] - hips[:, 1], axis=0)
    left -= up * (left @ up)
    left /= np.linalg.norm(left)
    basis = np.stack([np.cross(left, up), left, up])  # rows: x, y, z of the person frame
    out = j @ basis.T
    return out - np.nanmean(out, axis=1, keepdims=True)


def keypoint_frames(tracks: np.ndarray) -> np.ndarray:
    """Of a detector's keypoints (..., T, 13, 2), NaN where missed: the frames that count for
    calibration, where at least 4 joints are placed (..., T)."""
    return np.isfinite(tracks).all(axis=-1).sum(axis=-1) >= 4


def calibrate_rig(estimate: WalkEstimate, config: RigConfig = RigConfig(), *,
                  keypoints: np.ndarray | None = None) -> Rig:
    """The rig, the person's posture and body from an estimate's ``joints2d`` (this stage's entry).

    Needs ``joints2d`` measured on the silhouettes (:func:`estimator.mnbp.measure_postures`,
    which keeps the placement as ``model_joints2d``): self-calibrating the
    model's placement would calibrate the model's walk, so without them the
    viewpoints' rig is returned. Or ``keypoints``, (C, T, 13, 2) full-frame
    pixels of a detector's joints in the estimate's cameras and frames (NaN
    where missed; :meth:`RigConfig.for_keypoints`), calibrate it in their place:
    a frame counts for a camera where it sees 4 joints or more (:func:`keypoint_frames`). Cameras with
    postures on fewer than ``min_frames`` frames are left out of the
    self-calibration: their rotation is their viewpoint's (the viewpoints' rig
    relative to the reference), with no scale nor pinhole camera, and ``None``
    without a viewpoint. Never raises for the data: every fallback is the
    viewpoints' rig, or the scaled-orthographic one, with a note.
    """
    names = tuple(estimate.cameras)
    from_views = viewpoint_rotations(estimate)
    fallback = Rig(names, from_views, _box_scales(estimate), "viewpoints", height_m=config.height_m)
    if len(names) < 2:
        fallback.notes.append("one camera: no rig to calibrate")
        return fallback
    if keypoints is None:
        if all(c.model_joints2d is None for c in estimate.cameras.values()):
            fallback.notes.append("rig from the viewpoints: the 2D postures were not measured (posture 'model')")
            return fallback
        tracks = np.stack([estimate.cameras[n].joints2d for n in names])  # (C, T, 13, 2)
        posed = np.isfinite(tracks).all(axis=(2, 3))  # (C, T)
    else:
        tracks = np.asarray(keypoints, float)
        if tracks.shape != (len(names), len(estimate.phase), N_JOINTS, 2):
            raise ValueError(f"keypoints must have shape {(len(names), len(estimate.phase), N_JOINTS, 2)} "
                             f"(cameras, frames, joints, 2), got {tracks.shape}")
        posed = keypoint_frames(tracks)
    use = np.flatnonzero(posed.sum(axis=1) >= config.min_frames)
    seen = posed[use].sum(axis=0) >= 2
    if len(use) < 2 or seen.sum() < config.min_frames:
        fallback.notes.append(f"rig from the viewpoints: {int(seen.sum())} frames with postures from two cameras "
                              f"or more (self-calibration needs {config.min_frames})")
        return fallback
    frames = np.flatnonzero(seen)
    frames = frames[::int(np.ceil(len(frames) / config.max_frames))]  # evenly, at most max_frames
    if config.pinhole.smooth and not config.consecutive:  # frames from many windows: no motion between them
        config = replace(config, pinhole=replace(config.pinhole, smooth=0.0))
    views = from_views[use] @ from_views[use[0]].T
    below = hidden_joints(estimate, names) if keypoints is None else np.zeros(tracks.shape[:3], bool)
    start = frames
    if config.perspective and len(frames) > config.start_frames:  # the start: the middle frames in a row
        mid = len(frames) // 2 - config.start_frames // 2
        start = frames[mid:mid + config.start_frames]
        if np.any(posed[use][:, start].sum(axis=1) < config.min_frames):  # a camera hardly seen there
            start = frames
    try:
        smooth = config.consecutive and len(start) > 1 and bool(np.all(np.diff(start) == 1))
        cal = self_calibrate(tracks[use][:, start], refine=True, upright=config.upright,
                             initial_rotations=views if np.all(np.isfinite(views)) else None,
                             temporal_prior=None if smooth else False)
    except (ValueError, np.linalg.LinAlgError) as exc:
        cal = None
        fallback.notes.append(f"rig from the viewpoints: self-calibration failed ({exc})")
    if cal is not None and not cal:
        fallback.notes.append(f"rig from the viewpoints: self-calibration failed ({cal.reason})")
    if not cal:
        return fallback
    doubt = _view_doubt(estimate, [names[c] for c in use], config)
    fused, weight = _fuse(cal.rotations, cal.euler_xyz_std_deg, views, config.viewpoint_sigma_deg * doubt)
    low = None if keypoints is not None else _posture_weights(estimate, names, config)
    weights = _joint_weights(low, below, config)  # None for keypoints: no posture scores, nothing below
    weights = None if weights is None else weights[use][:, frames]
    used = tracks[use][:, frames]  # the postures the pinhole stages fit
    pinhole, why_not, pinhole_start = _pinhole(estimate, [names[c] for c in use], used, fused, cal.scales, config,
                                               views, weights, frames)
    changes = None
    if pinhole is not None and config.rounds > 1:
        pinhole, changes = iterate_rounds(estimate, [names[c] for c in use], frames, pinhole, config, views)
    tangent_note, tangents = "", None
    if pinhole is not None and config.tangents is not None:
        pinhole, tangent_note, tangents = _on_tangents(estimate, [names[c] for c in use], frames, used, pinhole,
                                                       config, weights)
    final = fused if pinhole is None else pinhole.rotations
    if pinhole is None:
        frames = start  # the posture is the scaled-orthographic adjustment's
    if np.all(np.isfinite(views)) and config.max_disagreement_deg > 0:
        apart = max(float(geodesic_deg(a, b)) for a, b in zip(final, views))
        if apart > config.max_disagreement_deg:  # a wrong basin (e.g. a depth flip), not a few degrees
            fallback.notes.append(f"rig from the viewpoints: the self-calibrated rig is {apart:.0f} deg from the "
                                  f"viewpoints' (more than {config.max_disagreement_deg:.0f}): taken as a wrong "
                                  "solution")
            return fallback
    smooth = pinhole is not None and config.smooth_posture and config.consecutive
    measured = _median_lengths(cal.joints3d if pinhole is None else pinhole.joints3d)  # before any smoothing:
    if smooth:  # averaging positions shortens moving limbs
        pinhole = replace(pinhole, joints3d=smoothed(pinhole.joints3d, frames))
    joints3d = person_frame(cal.joints3d if pinhole is None else pinhole.joints3d)
    k = _scale_for(measured, config.height_m)
    if not np.isfinite(k):
        fallback.notes.append("rig from the viewpoints: the self-calibrated body has no length")
        return fallback
    joints = np.full((tracks.shape[1], N_JOINTS, 3), np.nan)
    joints[frames] = joints3d * k
    segments = {n: v * k for n, v in measured.items()}

    def full(a: np.ndarray | None, fill: float = np.nan) -> np.ndarray | None:
        """Per-camera values of the calibrated cameras, spread over every camera (``fill`` elsewhere)."""
        if a is None:
            return None
        out = np.full((len(names), *np.shape(a)[1:]), fill)
        out[use] = a
        return out

    start_used = cal.diagnostics.get("start", "closed form")
    if pinhole is None:
        rig = Rig(names, full(fused), full(cal.scales), "self-calibration", full(cal.euler_xyz_std_deg),
                  full(cal.scale_std), joints, segments, config.height_m, reference=names[use[0]],
                  rotvec_cov=full(cal.rotvec_cov))
        how = f"scaled orthographic bundle adjustment from the {start_used}" + (f"; {why_not}" if why_not else "")
    else:
        rig = Rig(names, full(pinhole.rotations), full(pinhole.scales), "self-calibration", None, None, joints,
                  segments, config.height_m, reference=names[use[0]],
                  focal_px=full(pinhole.focal_px), centres_m=full(pinhole.centres * k),
                  walker_m=np.nanmean(pinhole.joints3d.reshape(-1, 3), axis=0) * k,
                  image_sizes=full(np.array([estimate.tracks[names[c]].image_size for c in use], float)),
                  joints2d=_projected(pinhole, use, frames, (len(names), tracks.shape[1])), tangents=tangents)
        how = (f"scaled orthographic bundle adjustment from the {start_used}"
               + (f" on the middle {len(start)} frames" if len(start) < len(frames) else "")
               + f", then pinhole cameras (reprojection {pinhole.rmse_px:.1f} px rms"
               + ("" if low is None or np.all(low[use][:, frames] == 1.0) else
                  f"; {int(np.sum(low[use][:, frames] < 1.0))} camera-frames whose posture explained its "
                  f"silhouette with a score under {config.posture_weight_below} weighed {_LOW_WEIGHT}")
               + ("" if not below[use][:, frames].any() else
                  f"; {int(below[use][:, frames].sum())} joints placed below a silhouette hidden below weighed "
                  f"{config.hidden_weight}")
               + ("" if weights is None or np.all(weights == 1.0) else
                  f", {_rms(pinhole, used, weights):.1f} px rms as weighed")
               + ")"
               + (f"; {tangent_note}" if tangent_note else "")
               + ("; the posture filtered [1, 2, 1] / 4 over neighbouring frames" if smooth else ""))
    rig.notes.append(f"rig and posture by self-calibration (Wang-Leow §4; {how}) on {len(frames)} frames"
                     + (" of the detector's keypoints" if keypoints is not None else "")
                     + (f" (every {frames[1] - frames[0]}th)" if len(frames) > 1 and frames[1] - frames[0] > 1 else "")
                     + f"; metres at a stature of {config.height_m} m")
    if changes is not None:
        rig.notes.append(f"{1 + len(changes)} rounds of posture and calibration (Wang-Leow §5: 3D mNBP over all "
                         "views, then the pinhole adjustment again); largest camera turn per round after the first: "
                         + (", ".join(f"{c:.2f} deg" for c in changes) or "none (the 3D round failed)"))
    if keypoints is not None and len(use) == 2:
        rig.notes.append("two cameras from a detector's keypoints: the rotation between two views of a person is "
                         "weakly determined; the silhouettes' viewpoints started the adjustment (2.4-6.7 deg in the "
                         "median of a draw of synthetic walks 4-15 m away, three or four cameras 0.4-1.9; "
                         "docs/POSTURE.md); a third camera settles it")
    elif len(use) == 2:
        rig.notes.append(TWO_VIEWS)
    rig.notes += [named_note(n, [names[c] for c in use]) for n in input_warnings(
        tracks[use][:, frames], final, cal.joints3d if pinhole is None else pinhole.joints3d)]
    few = [c for c in range(len(names)) if c not in use]
    viewed = [c for c in few if np.all(np.isfinite(from_views[c]))]
    if viewed:  # the viewpoints' rotation to the reference, as the viewpoints' rig would give it
        rig.rotations = np.array(rig.rotations, float)
        rig.rotations[viewed] = from_views[viewed] @ from_views[use[0]].T
        rig.notes.append(f"rotation from its viewpoint only, not self-calibrated (postures on fewer than "
                         f"{config.min_frames} frames): {', '.join(names[c] for c in viewed)}")
    left_out = [names[c] for c in few if c not in viewed]
    if left_out:
        rig.notes.append(f"not in the rig (postures on fewer than {config.min_frames} frames and no viewpoint): "
                         f"{', '.join(left_out)}")
    if weight is not None:
        rig.notes.append(("pinhole adjustment started from the " if pinhole is not None else "")
                         + "rotations fused with the viewpoints' rig by their errors (self-calibration's weight: "
                         + ", ".join(f"{names[c]} {w:.2f}" for c, w in zip(use[1:], weight[1:])) + ")"
                         + ("; also from the viewpoints' rig, whose end had the lower cost and was kept"
                            if pinhole_start[0] == "viewpoints" else ""))
    if pinhole_start[1] == "frames":
        rig.notes.append("pinhole adjustment kept from the start that places the walker at the depth its image size "
                         "gives in each frame, with the focal lengths that tells (its end had the lowest cost)")
    return rig


_SAME_START_DEG = 1.0  # the viewpoints' start is not tried when every camera starts this close to it


def _pinhole(estimate: WalkEstimate, names: list[str], tracks: np.ndarray, rotations: np.ndarray,
             scales: np.ndarray, config: RigConfig, views: np.ndarray, weights: np.ndarray | None = None,
             frames: np.ndarray | None = None) -> tuple[PerspectiveRig | None, str, tuple[str, str]]:
    """The pinhole adjustment when it can run and its result is sane: (rig, "", the start kept: its
    rotations' and its depths'), or (None, why not, ("", "")). ``weights`` (C, T, 13): each joint's
    (:func:`_joint_weights`); ``frames``: the tracks' frame numbers. With the viewpoints' prior it is
    started from ``rotations`` and, where they differ, from the viewpoints' rig
    (:attr:`RigConfig.pinhole_viewpoint_start`), each with the walker placed as each of
    :attr:`RigConfig.pinhole_depth_starts` says; the lowest cost wins."""
    if not config.perspective:
        return None, "", ("", "")
    tr = estimate.tracks or {}
    if not all(n in tr and tr[n].full_frame and tr[n].image_size is not None for n in names):
        return None, "no pinhole cameras: the silhouettes are crops without a full frame", ("", "")
    sizes = np.array([tr[n].image_size for n in names], float)
    prior = _viewpoint_prior(estimate, names, views, config)
    starts = {"fused": rotations}
    if (prior is not None and config.pinhole_viewpoint_start
            and max(float(geodesic_deg(a, b)) for a, b in zip(rotations, views)) > _SAME_START_DEG):
        starts["viewpoints"] = views
    epipolar = config.pinhole_epipolar_start and prior is None and len(names) >= 3  # one start then
    ends, why_not = {}, ""
    depths = ("fixed",) if epipolar else config.pinhole_depth_starts
    for (name, start), depth in itertools.product(starts.items(), depths):
        pc = replace(config.pinhole, depth_start=depth)
        try:
            if epipolar:
                pin, _ = refine_from_starts(tracks, sizes, start, scales, list(RIGID_LINKS), config=pc,
                                            frame_times=frames)
            else:
                pin = perspective_refine(tracks, sizes, start, scales, list(RIGID_LINKS), config=pc,
                                         rotation_prior=prior, weights=weights, frame_times=frames)
        except (ValueError, np.linalg.LinAlgError) as exc:
            why_not = f"the pinhole adjustment failed ({exc})"
            continue
        why_not = _insane(pin, estimate, names, config, tracks, weights)
        if not why_not:
            ends[name, depth] = pin
    if not ends:
        return None, why_not, ("", "")
    kept = min(ends, key=lambda k: ends[k].cost if np.isfinite(ends[k].cost) else np.inf)
    return ends[kept], "", kept


_LOW_WEIGHT = 0.05  # a camera-frame whose posture explains its silhouette badly (RigConfig.posture_weight_below)


def _posture_weights(estimate: WalkEstimate, names: tuple[str, ...], config: RigConfig) -> np.ndarray | None:
    """Each camera-frame's weight (C, T) in the pinhole adjustment: ``_LOW_WEIGHT`` where mNBP's
    posture explains its silhouette with a score under ``posture_weight_below``
    (:attr:`estimator.mnbp.Posture2D.score`), 1 elsewhere and where unscored. None when off or
    nothing is scored."""
    scores = [estimate.cameras[n].posture_score for n in names]
    if all(s is None for s in scores):
        return None
    t = len(estimate.phase)
    return _low_weights(np.stack([np.full(t, np.nan) if v is None else np.asarray(v, float) for v in scores]),
                        config)


def _joint_weights(frame_weights: np.ndarray | None, hidden: np.ndarray, config: RigConfig) -> np.ndarray | None:
    """Each camera's joint weights (C, T, 13) in the pinhole adjustment: the camera-frame's
    (``frame_weights`` (C, T), :func:`_posture_weights`), times ``config.hidden_weight`` for a joint
    ``hidden`` below its silhouette (:func:`hidden_joints`). None when all are 1."""
    if frame_weights is None and not hidden.any():
        return None
    frames = np.ones(hidden.shape[:2]) if frame_weights is None else frame_weights
    return frames[..., None] * np.where(hidden, config.hidden_weight, 1.0)


def _low_weights(scores: np.ndarray, config: RigConfig) -> np.ndarray | None:
    """``_LOW_WEIGHT`` where a posture's score (any shape) is under ``posture_weight_below``, 1 elsewhere
    and where unscored (NaN); None when off."""
    below = config.posture_weight_below
    return None if below is None else np.where(scores < below, _LOW_WEIGHT, 1.0)


def _num(value, digits: int):
    """``value`` (a number or an array) rounded for the result, None when any of it is not finite (strict
    JSON has no inf or NaN)."""
    return np.round(value, digits).tolist() if np.all(np.isfinite(value)) else None


def _on_tangents(estimate: WalkEstimate, names: list[str], frames: np.ndarray, tracks: np.ndarray,
                 pinhole: PerspectiveRig, config: RigConfig,
                 weights: np.ndarray | None = None) -> tuple[PerspectiveRig, str, dict]:
    """The pinhole rig adjusted to the silhouettes' epipolar tangents, the posture fitted again with
    those cameras held; or the rig as given when the tangents do not help. And what was done (a note
    and :attr:`Rig.tangents`)."""
    summary = {"used": False, "frame_pairs": 0, "residual_px": None, "largest_turn_deg": None,
               "rotation_std_deg": None, "held_directions": 0}
    tr = estimate.tracks
    shapes = [outlines(t.silhouettes, t.boxes, t.image_size, cut=t.cut, cut_band=config.tangents.cut_band)
              for t in (tr[n].take(frames) for n in names)]
    try:
        found = refine_on_tangents(pinhole.focal_px, pinhole.principal_px, pinhole.rotations, pinhole.centres,
                                   shapes, config.tangents)
    except (ValueError, np.linalg.LinAlgError) as exc:
        return pinhole, f"the epipolar tangents failed ({exc})", summary
    if found is None:
        return pinhole, "too few frames with epipolar tangents to refine on", summary
    before, after = found.residual_px
    turn = max(float(geodesic_deg(a, b)) for a, b in zip(found.rotations, pinhole.rotations))
    spread = float(found.rotation_std_deg.max())
    summary.update(frame_pairs=found.frames, residual_px=[_num(before, 3), _num(after, 3)],
                   largest_turn_deg=round(turn, 2), rotation_std_deg=_num(spread, 2), held_directions=found.held)
    if not np.isfinite(after):
        return pinhole, "epipolar tangents not used (the adjustment left no outline pair to measure)", summary
    holding = f", {found.held} direction{'s' * (found.held > 1)} of it held" if found.held else ""
    if not (after < before and after <= config.tangent_max_residual_px and turn <= config.tangent_max_turn_deg):
        return pinhole, (f"epipolar tangents not used (residual {before:.2f} -> {after:.2f} px, largest turn "
                         f"{turn:.1f} deg, rotations determined within {spread:.1f} deg{holding})"), summary
    sizes = np.array([tr[n].image_size for n in names], float)
    height = _walker_height(estimate, names)
    held = replace(config.pinhole, focal_px=tuple(float(f) for f in found.focal_px),
                   principal_px=tuple(tuple(float(v) for v in p) for p in pinhole.principal_px))
    moved = replace(pinhole, rotations=found.rotations, centres=found.centres, focal_px=found.focal_px)
    # the start: the joints triangulated by the new cameras; where a joint's rays nearly meet nowhere (its
    # reprojection off by more than a tenth of the walker), the old posture scaled about camera 0 as its
    # focal length (the walker's depth moves with it) and moved to where the frame's other joints went
    cams = moved.cameras()
    tri = triangulate(cams, tracks)
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames: no shift
        off = np.nanmax(np.linalg.norm(project(cams, tri) - tracks, axis=-1), axis=0)  # (T, J)
        good = np.isfinite(tri).all(axis=-1) & (off < 0.1 * height)
        scaled = pinhole.joints3d * (found.focal_px[0] / pinhole.focal_px[0])
        shift = np.nanmedian(np.where(good[..., None], tri - scaled, np.nan), axis=1, keepdims=True)
    # from the triangulated joints, and should that fit diverge (a joint triangulated behind a camera),
    # from the old posture moved as a whole
    why_not, whole = "", scaled + np.nan_to_num(shift)
    limit = 1.25 * _rms(pinhole, tracks, weights)  # see below
    for start in (np.where(good[..., None], tri, whole), whole):
        try:
            new = perspective_refine(tracks, sizes, None, None, list(RIGID_LINKS), config=held,
                                     initial=replace(moved, joints3d=start), weights=weights, frame_times=frames,
                                     rotation_prior=(found.rotations, config.tangent_hold * height * 180.0 / np.pi))
        except (ValueError, np.linalg.LinAlgError) as exc:
            why_not = f"the posture's fit failed: {exc}"
            continue
        # cameras held cannot follow the postures' own faults as free ones did: a refit up to a quarter
        # worse than the pinhole adjustment's is not a diverged one (cut limbs: 10.6 -> 11.2 px rms, while
        # the tangents took the cameras from 5.4 / 4.0 / 18.1 deg off to 0.2 / 0.2 / 1.4)
        why_not = _insane(new, estimate, names, config, tracks, weights, max_rms_px=limit)
        if not why_not:
            break
    if why_not:
        return pinhole, f"epipolar tangents not used ({why_not})", summary
    summary["used"] = True
    return new, (f"cameras refined on the silhouettes' epipolar tangents ({found.frames} frame pairs; residual "
                 f"{before:.2f} -> {after:.2f} px median; largest turn {turn:.1f} deg; rotations determined "
                 f"within {spread:.1f} deg{holding})"), summary


def hidden_joints(estimate: WalkEstimate, names: tuple[str, ...] | list[str]) -> np.ndarray:
    """(C, T, 13) True where a camera's 2D joint lies below a silhouette whose lowest part is hidden.

    A wall in front or the frame's bottom edge (:attr:`estimator.pipeline.CameraTrack.hidden`) leaves
    mNBP nothing to measure there: it places such a joint by the articulation alone
    (:class:`estimator.mnbp.SilhouetteView` scores those rows as unknown). The pinhole adjustment
    weighs it less (:attr:`RigConfig.hidden_weight`).
    """
    tracks = estimate.tracks or {}
    return np.stack([_below_silhouette(tracks.get(n), estimate.cameras[n].joints2d, len(estimate.phase))
                     for n in names])


def _below_silhouette(track: CameraTrack | None, joints: np.ndarray | None, frames: int) -> np.ndarray:
    """(T, 13) True where ``joints`` (T, 13, 2), full-frame pixels, lie under a silhouette of ``track``
    that has its lowest part hidden."""
    if track is None or track.hidden is None or not track.full_frame or joints is None:
        return np.zeros((frames, N_JOINTS), bool)
    bottom = track.boxes[:, 1] + track.boxes[:, 3]
    with np.errstate(invalid="ignore"):
        return (track.hidden > 0)[:, None] & (joints[..., 1] > bottom[:, None])


def _walker_height(estimate: WalkEstimate, names: list[str]) -> float:
    """The walker's median image height in pixels over the cameras ``names``, with what is hidden below."""
    return float(np.nanmedian(np.concatenate([estimate.tracks[n].whole_heights() for n in names])))


TWO_VIEWS = ("two cameras: the rotation between two views of a person is weakly determined (a direction of it "
             "the epipolar tangents cannot see); on videos of a walker composited into real footage, 7 two-camera "
             "rigs were 1.7-11.4 deg off (median 3.7) against 4.0-11.7 (7.2) from the viewpoints, 1 of them worse "
             "by more than 2 deg (docs/ROBUSTNESS.md, \"Two starts of the pinhole adjustment\"); a third camera "
             "settles it, and --posture model (posture=model in a job) gives the viewpoints' rig")
"""The note of a rig calibrated on the postures of two cameras (docs/ROBUSTNESS.md, "Two cameras")."""


def _view_doubt(estimate: WalkEstimate, names: list[str], config: RigConfig) -> np.ndarray:
    """(C,) How many times less sure than usual each camera's rotation from the viewpoints is,
    relative to the first camera's (``config.hidden_view_doubt`` for a walker hidden below)."""
    tracks = estimate.tracks or {}
    hidden = np.array([n in tracks and tracks[n].hidden is not None and np.mean(tracks[n].hidden > 0) >= 0.5
                       for n in names])
    doubt = np.where(hidden, config.hidden_view_doubt, 1.0)
    return np.sqrt((doubt**2 + doubt[0] ** 2) / 2.0)


def _viewpoint_prior(estimate: WalkEstimate, names: list[str], views: np.ndarray, config: RigConfig):
    """The viewpoints' rotations as a prior of the pinhole adjustment, or None; its weight per camera."""
    if config.pinhole_viewpoint_weight <= 0 or not np.all(np.isfinite(views)):
        return None
    height = _walker_height(estimate, names)
    return views, config.pinhole_viewpoint_weight * height * 180.0 / np.pi / _view_doubt(estimate, names, config)


def _rms(pin: PerspectiveRig, tracks: np.ndarray, weights: np.ndarray | None) -> float:
    """The pinhole result's reprojection rms over ``tracks`` (C, T, 13, 2), each joint counted by its
    ``weights`` (C, T, 1) or (C, T, 13) as the adjustment counted it (``pin.rmse_px`` without weights)."""
    if weights is None:
        return pin.rmse_px
    d = np.linalg.norm(project(pin.cameras(), pin.joints3d) - tracks, axis=-1)
    ok = np.isfinite(tracks).all(axis=-1)
    if not np.isfinite(d[ok]).all():
        return np.inf  # an observed joint projected nowhere: a diverged fit
    w = np.broadcast_to(weights, d.shape)[ok]
    return float(np.sqrt(np.sum(w * d[ok] ** 2) / max(np.sum(w), 1e-12)))


def _insane(pin: PerspectiveRig, estimate: WalkEstimate, names: list[str], config: RigConfig,
            tracks: np.ndarray | None = None, weights: np.ndarray | None = None, *,
            max_rms_px: float = 0.0) -> str:
    """Why a pinhole result is refused (a diverged fit), or "" when it is sane; its reprojection
    onto ``tracks`` as the adjustment weighed it (:func:`_rms`; ``pin.rmse_px`` without tracks) may
    reach ``config.pinhole_max_rms`` of the walker's height or ``max_rms_px``, the larger."""
    rms = pin.rmse_px if tracks is None else _rms(pin, tracks, weights)
    tr = estimate.tracks
    height = _walker_height(estimate, names)
    widths = pin.focal_px / np.array([tr[n].image_size[0] for n in names], float)
    lo, hi = config.pinhole_focal_widths
    if not (np.all(np.isfinite(pin.rotations)) and np.all((widths > lo) & (widths < hi))
            and rms <= max(config.pinhole_max_rms * height, max_rms_px)):
        return (f"pinhole cameras refused (focal lengths {np.round(widths, 2).tolist()} image widths, "
                f"reprojection {rms:.1f} px rms)")
    return ""


@dataclass
class RigAccumulator:
    """A fixed rig calibrated over many short windows (the live service's rig).

    Windows are short so that viewpoints can be taken as fixed relative to
    the walker; the cameras themselves are fixed for much longer, and the
    self-calibration wants more frames than a window has. Each window adds
    the mNBP postures of at most ``frames_per_window`` of its frames not seen
    before (evenly spread: mNBP costs about 30 ms per frame and camera, so a
    window's worth would not keep up with live rates); :meth:`calibrate` runs
    :func:`calibrate_rig` on the last ``config.max_frames`` of them joined in
    time (:func:`estimator.pipeline.concat_estimates`). :meth:`reset` when a
    camera moved.

    A window that comes with a detector's keypoints (two cameras or more)
    adds every new frame instead, with nothing to measure, and the rig is
    calibrated from the keypoints (:meth:`RigConfig.keypoint_settings`); the
    postures kept before are dropped, and from then on windows without
    keypoints add nothing until :meth:`reset`.
    """

    config: RigConfig = field(default_factory=RigConfig)  # calibrated with consecutive=False, whatever it says
    posture: MNBPConfig = field(default_factory=MNBPConfig)
    frames_per_window: int = 2
    _parts: list[WalkEstimate] = field(default_factory=list, repr=False)
    _indices: list[np.ndarray] = field(default_factory=list, repr=False)  # each part's frame indices
    _keypoints: list[dict[str, np.ndarray]] | None = field(default=None, repr=False)  # per part, once detected
    _last_index: int = -1
    windows: int = 0

    @property
    def from_keypoints(self) -> bool:
        """Whether the rig is calibrated from a detector's keypoints (rather than mNBP postures)."""
        return self._keypoints is not None

    def add(self, estimate: WalkEstimate, first_index: int,
            keypoints: dict[str, np.ndarray] | None = None, *, indices: np.ndarray | None = None) -> int:
        """Add the new frames of a window starting at frame ``first_index``: their measured postures,
        or with ``keypoints`` (camera -> (T, 13, 2) pixels of the window's frames, NaN where missed)
        the detector's joints; how many frames. ``indices``: the window's frame indices when they
        are not consecutive (a live window across a gap in the stream)."""
        n = len(estimate.phase)
        index = first_index + np.arange(n) if indices is None else np.asarray(indices, int)
        if index.shape != (n,):
            raise ValueError(f"indices must give the window's {n} frames, got shape {index.shape}")
        detected = keypoints is not None and sum(bool(keypoint_frames(np.asarray(k, float)).any())
                                                 for c, k in keypoints.items() if c in estimate.cameras) >= 2
        if detected and not self.from_keypoints:  # the keypoints replace the postures measured so far
            self.reset()
            self._keypoints = []
        new = np.flatnonzero(index > self._last_index)
        if not len(new) or (self.from_keypoints and not detected) or (not detected and self.frames_per_window < 1):
            return 0
        if detected:  # every new frame: there is nothing to measure
            pick = new
            self._parts.append(take_frames(estimate, pick))
            self._keypoints.append({c: np.asarray(k, float)[pick] for c, k in keypoints.items()})
        else:
            pick = np.unique(new[np.linspace(0, len(new) - 1,
                                             min(self.frames_per_window, len(new))).round().astype(int)])
            self._parts.append(measure_postures(take_frames(estimate, pick), self.posture))
        self._indices.append(index[pick])
        self._last_index = int(index.max())
        self.windows += 1
        while self.n_frames - len(self._parts[0].phase) >= self.config.max_frames:
            self._parts.pop(0)
            self._indices.pop(0)
            if self._keypoints:
                self._keypoints.pop(0)
        return len(pick)

    @property
    def n_frames(self) -> int:
        """Frames with measured postures kept."""
        return sum(len(p.phase) for p in self._parts)

    @property
    def frame_indices(self) -> np.ndarray:
        """The frame index of each frame kept, in the order :meth:`calibrate` sees them."""
        return np.concatenate(self._indices) if self._indices else np.zeros(0, int)

    def calibrate(self, viewpoints: dict[str, tuple[float, float]] | None = None) -> Rig:
        """The rig over the frames kept (the viewpoints' rig, with a note, while they are too few).

        ``viewpoints`` (camera -> azimuth, elevation in degrees) replace the kept windows' own
        (:func:`~estimator.pipeline.concat_estimates`: their medoid, which of two windows that
        disagree is the first): the live service gives its smoothed ones, over every window
        since the last camera move (:class:`~estimator.windows.ViewpointTrack`), of which the
        kept windows are a few.
        """
        if not self._parts:
            raise ValueError("no window added yet")
        joined = concat_estimates(self._parts)
        if viewpoints:
            joined = replace(joined, cameras={
                n: c if n not in viewpoints else replace(c, viewpoint=replace(
                    c.viewpoint, azimuth_deg=float(viewpoints[n][0]), elevation_deg=float(viewpoints[n][1])))
                for n, c in joined.cameras.items()})
        if not self.from_keypoints:
            return calibrate_rig(joined, replace(self.config, consecutive=False))
        kp = np.stack([np.concatenate([k.get(c, np.full((len(p.phase), N_JOINTS, 2), np.nan))
                                       for p, k in zip(self._parts, self._keypoints)]) for c in joined.cameras])
        return calibrate_rig(joined, replace(self.config, consecutive=False, **self.config.keypoint_settings()),
                             keypoints=kp)

    def newest_posture(self, rig: Rig) -> tuple[int, np.ndarray] | None:
        """The newest frame of :meth:`calibrate`'s ``rig`` with the whole person's posture: its
        frame index and joints (13, 3) (person frame, metres); None when there is none."""
        if rig.joints3d is None:
            return None
        whole = np.flatnonzero(np.isfinite(rig.joints3d).all(axis=(1, 2)))
        if not len(whole):
            return None
        return int(self.frame_indices[whole[-1]]), np.asarray(rig.joints3d[whole[-1]], float)

    def reset(self) -> None:
        """Forget every frame (a camera moved: the rig is another one)."""
        self._parts.clear()
        self._indices.clear()
        self._keypoints = None
        self._last_index, self.windows = -1, 0


def iterate_rounds(estimate: WalkEstimate, names: list[str], frames: np.ndarray, pinhole: PerspectiveRig,
                   config: RigConfig, views: np.ndarray) -> tuple[PerspectiveRig, list[float]]:
    """Wang–Leow §5: 3D mNBP with the calibrated cameras, then self-calibration again.

    Each round measures the 3D posture on every view's silhouette at once
    (:func:`estimator.mnbp3d.posture_sequence3d`, started from the current
    joints), projects it into each camera, lets each view correct the
    projection on its own silhouette (``config.polish``, a short 2D mNBP
    centred on it; without it the projections fit the current cameras
    exactly and the rig could not move) and adjusts the pinhole cameras to
    those 2D joints from the current ones, each view-frame weighed by its
    polished posture's score as round one's are (``posture_weight_below``);
    the parts are the person's width (:func:`estimator.mnbp.person_widths`,
    read once). Stops after ``config.rounds``
    (counting the 2D round) or when no camera turns by ``converged_deg``.
    Returns the last pinhole result and each round's largest rotation change.
    """
    tr = estimate.tracks
    sizes = np.array([tr[n].image_size for n in names], float)
    taken = [tr[n].take(frames) for n in names]
    sils = [t.silhouettes for t in taken]
    boxes = np.stack([t.boxes for t in taken]).astype(float)
    stature = config.height_m / stature_scale(pinhole.joints3d, config.height_m)
    # The person's part widths, read once where round one's posture projects (as the 2D round
    # reads them on its starts), serve every view of the 3D round and each view's polish.
    hidden = [t.hidden for t in taken]
    widths = (person_widths(sils, list(boxes), list(project(pinhole.cameras(), pinhole.joints3d)), hidden=hidden)
              if config.round3d.mnbp.fit_widths else None)
    changes = []
    for r in range(1, config.rounds):
        cams = pinhole.cameras()
        joints3d, _ = posture_sequence3d(sils, boxes, cams, pinhole.joints3d, stature=stature,
                                         config=config.round3d, seed=1000 * r, widths=widths, hidden=hidden)
        tracks, weights = project(cams, joints3d), None
        if config.polish is not None:
            polished, scores = posture_sequences(sils, list(boxes), list(tracks), carry=0.0, config=config.polish,
                                                 seeds=[1000 * r + 100 * c for c in range(len(names))],
                                                 widths=widths, hidden=hidden)
            tracks = np.stack(polished)
            below = np.stack([_below_silhouette(t, j, len(frames)) for t, j in zip(taken, tracks)])
            weights = _joint_weights(_low_weights(np.stack(scores), config), below, config)  # as round one's
        try:
            new = perspective_refine(tracks, sizes, pinhole.rotations, pinhole.scales, list(RIGID_LINKS),
                                     config=config.pinhole, initial=replace(pinhole, joints3d=joints3d),
                                     rotation_prior=_viewpoint_prior(estimate, names, views, config),
                                     weights=weights, frame_times=frames)
        except (ValueError, np.linalg.LinAlgError):
            break
        if _insane(new, estimate, names, config, tracks, weights):
            break
        changes.append(max(float(geodesic_deg(a, b)) for a, b in zip(new.rotations, pinhole.rotations)))
        pinhole = new
        if changes[-1] < config.converged_deg:
            break
    return pinhole, changes


def smoothed(joints3d: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """``joints3d`` (T, J, 3) on ``frames`` (T,) filtered ``[1, 2, 1] / 4`` in time where a frame's two
    neighbours are the frames just before and after it; other frames, and NaN neighbours, as given."""
    out = np.array(joints3d, float)
    if len(frames) < 3:
        return out
    prev, mid, nxt = out[:-2], out[1:-1], out[2:]
    inner = (np.diff(frames[:-1]) == 1) & (np.diff(frames[1:]) == 1)
    ok = inner[:, None, None] & np.isfinite(prev) & np.isfinite(nxt) & np.isfinite(mid)
    out[1:-1] = np.where(ok, 0.25 * prev + 0.5 * mid + 0.25 * nxt, mid)
    return out


def _projected(pinhole: PerspectiveRig, use: np.ndarray, frames: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """The adjusted posture (on ``frames``) through the cameras ``use``: (C, T, 13, 2), NaN elsewhere."""
    out = np.full((*shape, N_JOINTS, 2), np.nan)
    out[np.ix_(use, frames)] = project(pinhole.cameras(), pinhole.joints3d)
    return out


def attach_rig(estimate: WalkEstimate, rig: Rig) -> WalkEstimate:
    """The estimate with its rig, and each camera's ``joints2d`` the rig's projected posture where it has one.

    Wang–Leow §5: with the cameras calibrated, the views' images combine in
    each 2D posture. The pinhole adjustment's 3D posture, fitted to every
    view's mNBP joints under constant bone lengths, projected back into a
    camera is nearer the truth than that camera's own mNBP (2D error / walker
    height, 6 walks each: CMU 0.0217 / 0.0526 -> 0.0212 / 0.0453 median / p90,
    stylised 0.0215 / 0.0515 -> 0.0207 / 0.0452; docs/POSTURE.md). Frames the
    adjustment did not use, and cameras outside the rig, keep their own.
    """
    if rig.joints2d is None:
        return replace(estimate, rig=rig)
    cams, replaced = {}, 0
    for k, (name, c) in enumerate(estimate.cameras.items()):
        proj = rig.joints2d[k]
        ok = np.isfinite(proj).all(axis=(1, 2)) & np.isfinite(c.joints2d).all(axis=(1, 2))
        replaced = max(replaced, int(ok.sum()))
        cams[name] = replace(c, joints2d=np.where(ok[:, None, None], proj, c.joints2d))
    notes = [*estimate.notes, f"joints2d: the person's 3D posture projected through the calibrated cameras on "
                              f"{replaced} of {len(estimate.phase)} frames (all views' postures at once); "
                              "elsewhere each view's own"]
    return replace(estimate, rig=rig, cameras=cams, notes=notes)


def _fuse(rotations: np.ndarray, std_deg: np.ndarray | None, views: np.ndarray,
          sigma_views: float | np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """Each camera's rotation on the geodesic from the viewpoints' to the self-calibration's,
    at the self-calibration's inverse-variance weight (``sigma_views``: the viewpoints' error, deg,
    one or per camera); (rotations, weights) or unchanged and None."""
    sigma_views = np.broadcast_to(np.asarray(sigma_views, float), (len(rotations),))
    if np.all(sigma_views <= 0) or std_deg is None or not np.all(np.isfinite(views)):
        return rotations, None
    sigma = np.linalg.norm(np.asarray(std_deg, float), axis=1)
    weight = np.where(np.isfinite(sigma), sigma_views**2 / (sigma_views**2 + sigma**2), 0.0)
    weight[0] = 1.0
    delta = Rotation.from_matrix(rotations) * Rotation.from_matrix(views).inv()  # views -> self-calibration
    fused = (Rotation.from_rotvec(delta.as_rotvec() * weight[:, None]) * Rotation.from_matrix(views)).as_matrix()
    return fused, weight


def _box_scales(estimate: WalkEstimate) -> np.ndarray:
    """Each camera's image scale relative to the first: ratio of median walker heights, with what is hidden
    below (1 without tracks)."""
    if estimate.tracks is None:
        return np.ones(len(estimate.cameras))
    heights = [estimate.tracks[n].whole_heights() if n in estimate.tracks else np.array([np.nan])
               for n in estimate.cameras]
    h = np.array([np.nanmedian(b) if np.isfinite(b).any() else np.nan for b in heights])  # no box: unknown
    return np.where(np.isfinite(h), h / h[0], 1.0) if np.isfinite(h[0]) else np.ones(len(h))
