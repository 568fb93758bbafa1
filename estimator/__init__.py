"""posecal's pure computation: numpy arrays and dataclasses in and out.

Nothing here touches the network, the web framework or Rerun. The names below
are what the capture agents and the service may call; everything else is an
implementation detail.
"""

from .body import PARTS, BodyPart
from .camera import Camera, viewpoint_direction, world_to_camera_rotation
from .examples import Examples
from .gait import GaitModel, GaitStyle, fit_gait, heel_strikes, load_gait, motion_angles, motion_phase
from .joints import BONES, JOINT_INDEX, JOINT_NAMES, MIRROR, N_JOINTS
from .mocap import Motion, read_asf_amc, read_bvh, read_motion
from .render import Renderer
from .sequence import Sequence, SequenceError, read_sequence, write_sequence
from .skeleton import FULL_JOINT_NAMES, BodyShape, GaitAngles, forward_kinematics, segment_angles
from .synth import SynthSpec, synthesize, walk

__all__ = [
    "BONES",
    "FULL_JOINT_NAMES",
    "JOINT_INDEX",
    "JOINT_NAMES",
    "MIRROR",
    "N_JOINTS",
    "PARTS",
    "BodyPart",
    "BodyShape",
    "Camera",
    "Examples",
    "GaitAngles",
    "GaitModel",
    "GaitStyle",
    "Motion",
    "Renderer",
    "Sequence",
    "SequenceError",
    "SynthSpec",
    "fit_gait",
    "forward_kinematics",
    "heel_strikes",
    "load_gait",
    "motion_angles",
    "motion_phase",
    "read_asf_amc",
    "read_bvh",
    "read_motion",
    "read_sequence",
    "segment_angles",
    "synthesize",
    "viewpoint_direction",
    "walk",
    "world_to_camera_rotation",
    "write_sequence",
]
