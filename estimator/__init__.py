"""posecal's pure computation: numpy arrays and dataclasses in and out.

Nothing here touches the network, the web framework or Rerun. The names below
are what the capture agents and the service may call; everything else is an
implementation detail.
"""

from .appearance import (
    AppearanceModel,
    BuildParams,
    build_model,
    choose_n_clusters,
    default_model,
    load_model,
    save_model,
    within_scatter_curve,
)
from .body import PARTS, BodyPart
from .camera import Camera, viewpoint_direction, world_to_camera_rotation
from .examples import ExampleGrid, Examples, render_examples
from .exemplars import ExemplarIndex
from .hmm import PhaseHMM, cyclic_transitions, phase_log_emission, viterbi
from .gait import GaitModel, GaitStyle, fit_gait, heel_strikes, load_gait, motion_angles, motion_phase
from .joints import BONES, JOINT_INDEX, JOINT_NAMES, MIRROR, N_JOINTS
from .keypoints import SKELETONS, Skeleton, detect_skeleton, keypoints_to_joints, track_person
from .mocap import Motion, read_asf_amc, read_bvh, read_motion
from .pinhole import PinholeCameras, floor_frame, triangulate
from .pipeline import CameraTrack, EstimateConfig, WalkEstimate, estimate_walk, tracks_from_sequence
from .registration import Transforms, transform_points
from .render import Renderer
from .sequence import Sequence, SequenceError, read_sequence, write_sequence
from .selfcal import RIGID_LINKS, SYMMETRIC_RATIOS, SelfCalibration, self_calibrate
from .selfcal_baselines import liebowitz_carlsson, tresadern_reid
from .skeleton import FULL_JOINT_NAMES, BodyShape, GaitAngles, forward_kinematics, segment_angles
from .synth import SynthSpec, place_cameras, synthesize, walk
from .viewpoint import MotionCue, Viewpoint, estimate_viewpoint, motion_cue

__all__ = [
    "BONES",
    "FULL_JOINT_NAMES",
    "JOINT_INDEX",
    "JOINT_NAMES",
    "MIRROR",
    "N_JOINTS",
    "PARTS",
    "RIGID_LINKS",
    "SKELETONS",
    "SYMMETRIC_RATIOS",
    "AppearanceModel",
    "BodyPart",
    "BodyShape",
    "BuildParams",
    "Camera",
    "CameraTrack",
    "EstimateConfig",
    "ExampleGrid",
    "Examples",
    "ExemplarIndex",
    "GaitAngles",
    "GaitModel",
    "GaitStyle",
    "Motion",
    "MotionCue",
    "PhaseHMM",
    "PinholeCameras",
    "Renderer",
    "SelfCalibration",
    "Sequence",
    "SequenceError",
    "Skeleton",
    "SynthSpec",
    "Transforms",
    "Viewpoint",
    "WalkEstimate",
    "build_model",
    "choose_n_clusters",
    "cyclic_transitions",
    "default_model",
    "detect_skeleton",
    "estimate_viewpoint",
    "estimate_walk",
    "fit_gait",
    "floor_frame",
    "forward_kinematics",
    "heel_strikes",
    "keypoints_to_joints",
    "liebowitz_carlsson",
    "load_gait",
    "load_model",
    "motion_angles",
    "motion_cue",
    "motion_phase",
    "phase_log_emission",
    "place_cameras",
    "read_asf_amc",
    "read_bvh",
    "read_motion",
    "read_sequence",
    "render_examples",
    "save_model",
    "segment_angles",
    "self_calibrate",
    "synthesize",
    "track_person",
    "tracks_from_sequence",
    "transform_points",
    "triangulate",
    "tresadern_reid",
    "viewpoint_direction",
    "viterbi",
    "walk",
    "within_scatter_curve",
    "world_to_camera_rotation",
    "write_sequence",
]
