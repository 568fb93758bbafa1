"""Response models of the REST API (storage rows and live state are converted here)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from .jobs import JobRow

__all__ = ["ErrorOut", "EstimatesOut", "Health", "JobList", "JobOut", "LiveCalibration", "LiveEstimate", "Result", "RigList", "RigOut",
           "error_responses", "job_out"]

JobState = Literal["queued", "running", "done", "failed", "cancelled"]


class JobOut(BaseModel):
    """A batch job as the API shows it."""

    id: str
    state: JobState
    kind: Literal["sequence", "videos"]
    progress: float = Field(description="0..1")
    stage: str = Field(description="what the job is doing now")
    error: str | None = None
    cameras: list[str] = []
    n_frames: int | None = None
    attempts: int
    created_at: datetime
    started_at: datetime | None = None
    finished_at: datetime | None = None
    links: dict[str, str]


def job_out(row: JobRow) -> JobOut:
    base = f"/v1/jobs/{row.id}"
    links = {"self": base, "cancel": f"{base}/cancel"}
    if row.has_result:
        links["result"] = f"{base}/result"
    return JobOut(id=row.id, state=row.state, kind=row.kind, progress=round(row.progress, 4),
                  stage=row.stage, error=row.error, cameras=row.options.get("cameras", []),
                  n_frames=row.options.get("n_frames"), attempts=row.attempts,
                  created_at=row.created_at, started_at=row.started_at,
                  finished_at=row.finished_at, links=links)


class JobList(BaseModel):
    jobs: list[JobOut]
    counts: dict[str, int]


class CameraQuality(BaseModel):
    """The agent's segmentation quality over its recent frames (``capture.wire.Quality``)."""

    walker_fraction: float = Field(description="share of frames in which a walker was found, 0..1")
    area_median: float = Field(description="median silhouette area, full-frame pixels")
    stability: float | None = Field(description="median box IoU of consecutive silhouettes, 0..1 "
                                    "(low = flickering or jumping); null before two in a row")


class CameraOut(BaseModel):
    frames: int
    last_index: int = Field(description="the rig's frame index of the camera's last frame (the agent's "
                            "own index plus index_offset)")
    last_seen_ns: int = Field(description="when its last frame arrived (the service's clock, ns)")
    last_seen_s_ago: float | None = Field(None, description="seconds since its last frame arrived")
    stale: bool = Field(False, description="silent for longer than camera_timeout_s: no longer waited "
                        "for, left out of new windows")
    in_windows: bool = Field(False, description="the rig's latest estimated window includes it")
    index_offset: int = Field(0, description="added to the agent's frame indices: non-zero after a "
                              "restarted index-synchronised agent was re-based onto the rig's frames")
    epoch_ns: int
    sync: str
    image_size: list[int]
    n_candidates: int | None = Field(None, description="person-sized components in the camera's "
                                     "last frame; > 1: several people in view, the agent sends "
                                     "the walker it tracks (null: the agent does not report it)")
    quality: CameraQuality | None = Field(None, description="the agent's latest quality figures "
                                          "(null until it reports them)")


class WindowCounts(BaseModel):
    seq: int = Field(description="windows cut so far; estimates carry their seq")
    estimated: int
    skipped: int = Field(description="too few silhouettes (walker absent) or nothing to match")
    failed: int
    dropped: int = Field(description="dropped because estimation fell behind")
    revised: int = Field(0, description="estimated again after a move of an agent's look back (window.revision)")


class FrameCounts(BaseModel):
    late: int
    duplicate: int
    missing: int = Field(description="camera frames absent when a frame set closed")
    restarts: int = Field(description="agent restarts (new epochs)")
    realigned: int = Field(0, description="restarts of index-synchronised agents whose frame indices were "
                           "re-based onto the rig's (the others kept theirs: no window lost)")
    gaps: int = Field(description="frame index jumps that restarted the window")
    index_ahead: int = Field(0, description="silhouettes dropped: frame_index too far ahead of the rig's "
                             "(max_index_ahead), until a few in a row agree")


class FeedbackCounts(BaseModel):
    enabled: bool = Field(description="priors are published to the segmenters (§7.1)")
    priors_sent: int = Field(description="priors published on posecal/<rig>/<camera>/feedback")


class SmoothedViewpoint(BaseModel):
    azimuth_deg: float | None
    elevation_deg: float | None
    windows: int
    pending_outliers: int
    outliers: int
    changes: list[dict[str, Any]] = Field(description="detected camera moves: frame_index, from, to")
    last_seen_s_ago: float | None = Field(None, description="seconds since the camera's last frame")
    stale: bool = Field(False, description="the camera has been silent for longer than camera_timeout_s: "
                        "this is its last viewpoint, not a current one")


class RigOut(BaseModel):
    rig: str
    cameras: dict[str, CameraOut]
    windows: WindowCounts
    frames: FrameCounts
    feedback: FeedbackCounts
    viewpoints: dict[str, SmoothedViewpoint]
    latest_seq: int | None


class RigList(BaseModel):
    live: bool
    rigs: list[RigOut]


class Health(BaseModel):
    status: Literal["ok"]
    live: bool
    zenoh_listen: list[str]
    rerun: str | None
    model: str
    jobs: dict[str, int]


# ----------------------------------------------------------------------------- results (docs/FORMATS.md, Result)
# These models publish the result's JSON Schema in OpenAPI (``responses=``); the routes return the
# stored dict as it is (no validation per request). ``tests/test_schemas.py`` validates real results
# against them with unknown keys forbidden, so a key the code writes and this file lacks fails there.

Joint2D = list[float]
Joint3D = list[float]


class _Open(BaseModel):
    model_config = ConfigDict(extra="allow")


class MotionCue(_Open):
    growth_per_frame: float = Field(description="relative change of the walker's image size per frame, > 0 approaching")
    growth_se: float | None = Field(description="standard error of growth_per_frame")
    growth_from: Literal["height", "head", "head+height", "head width", "head+head width", "none"]
    growth_contested: bool = Field(False, description="head and height disagreed: one was dropped, and the "
                                   "other cameras' phase may settle ahead/behind (flip 'cameras')")
    travel_heights_per_frame: float = Field(description="horizontal motion per frame in body heights, > 0 rightwards")


class ResultCamera(_Open):
    """A camera's viewpoint relative to the walker (docs/FORMATS.md, cameras)."""

    azimuth_deg: float | None = Field(description="null when the camera saw no silhouette")
    elevation_deg: float | None
    spread_deg: float | None
    covariance_deg2: list[list[float]] | None
    flip: str = Field(description="how ahead/behind was settled: motion, cameras, earlier, majority or none")
    flip_margin: float | None
    n_samples: int
    elevation_from: Literal["shape", "shape+path"] = Field(
        "shape", description="the elevation from the matched examples' viewpoints, or joined with the one the "
                             "walker's straight path across the image implies")
    motion_cue: MotionCue | None
    phase_offset: float | None = Field(None, description=(
        "median distance (cycles, 0-0.5) between the camera's per-frame phase observations and the phase "
        "decoded from every camera; null with fewer than 3 observations and on the paper's path: a camera "
        "out of step with the others (over 0.2 with two or more cameras, said in its notes) has a doubtful "
        "viewpoint"))
    notes: list[str]
    decoded_frames: int | None = Field(None, description="videos: frames that decoded")
    header_frames: int | None = Field(None, description="videos: frames the header counts (0: none given)")


class ResultFrame(_Open):
    """One frame (docs/FORMATS.md, frames)."""

    index: int
    phase: float | None = Field(description="walking phase in cycles [0, 1), the HMM's Viterbi path")
    seen_by: list[str] | None = Field(None, description="cameras with a silhouette in this frame")
    predicted: bool | None = Field(None, description="no camera observed the phase here: the HMM's prediction")
    phase_confidence: float | None = Field(None, description="posterior mass within one state of phase")
    phase_posterior: list[float] | None = Field(None, description="posterior over the HMM's 20 states")
    joints3d: list[Joint3D] | None = Field(description="the gait model at the phase, person frame, metres")
    person_joints3d: list[Joint3D | None] | None = Field(
        None, description="the person's posture from the self-calibrated rig, person frame, metres")
    joints2d: dict[str, list[Joint2D]] = Field(description="camera -> 13 joints, full-frame pixels")
    observed_phase: dict[str, float | None]
    model_joints2d: dict[str, list[Joint2D]] | None = None
    segment: int | None = None


class Hmm(_Open):
    log_prob: float | None
    half_cycle_margin: float | None


class RigCamera(_Open):
    rotation: list[list[float]] | None = Field(description="R_c R_ref^T; null for a camera left out of the rig")
    rotvec: list[float] | None = Field(description="the rotation as a rotation vector (radians)")
    quaternion_xyzw: list[float] | None = Field(None, description="the rotation as a unit quaternion, scalar "
                                                "last (x, y, z, w), w >= 0")
    euler_xyz_deg: list[float] | None
    scale: float | None
    focal_px: float | None = None
    centre_m: list[float] | None = None
    image_size: list[int] | None = Field(None, description="pinhole cameras: [width, height] in pixels; the "
                                         "principal point is its centre")
    euler_xyz_std_deg: list[float] | None = None
    rotvec_covariance_rad2: list[list[float]] | None = Field(
        None, description="scaled-orthographic self-calibration: posterior covariance (radians^2) of the "
        "rotation error as a rotation vector in this camera's axes (no gimbal lock, unlike euler_xyz_std_deg)")
    scale_std: float | None = None


class EpipolarTangents(_Open):
    """The refinement of pinhole cameras on the silhouettes' epipolar tangents (docs/POSTURE.md, step 5)."""

    used: bool = Field(description="the rig's cameras are the refined ones")
    frame_pairs: int = Field(description="frames of tangents over the camera pairs")
    residual_px: list[float | None] | None = Field(description="median tangent residual before and after, pixels "
                                                   "(after: null when the adjusted cameras left no outline "
                                                   "pair to measure)")
    largest_turn_deg: float | None
    rotation_std_deg: float | None = Field(description="how well the tangents alone determine the rotations "
                                           "(degrees; over 1.5 the directions they hardly see are held)")
    held_directions: int = Field(0, description="rotation directions held where the pinhole rig put them")


class RigResult(_Open):
    """The calibrated rig (docs/FORMATS.md, rig)."""

    reference: str
    source: Literal["self-calibration", "viewpoints"]
    cameras: dict[str, RigCamera]
    epipolar_tangents: EpipolarTangents | None = None


class BodySegment(_Open):
    metres: float
    relative: float


class Body(_Open):
    stature_m: float
    segments: dict[str, BodySegment]


class WindowViewpoint(_Open):
    azimuth_deg: float | None
    elevation_deg: float | None


class SegmentOut(_Open):
    first_index: int
    last_index: int
    windows: int
    cameras: dict[str, ResultCamera] | None = None
    hmm: Hmm | None = None
    notes: list[str] | None = None
    rig: RigResult | None = None
    body: Body | None = None
    error: str | None = None


class WindowOut(_Open):
    first_index: int
    last_index: int
    segment: int
    cameras: dict[str, WindowViewpoint | None] | None = None
    error: str | None = None


class _ResultBase(_Open):
    schema_version: int = Field(description="version of this layout (docs/FORMATS.md)")
    units: dict[str, str]
    coordinate_frames: dict[str, str]
    joint_names: list[str]
    cameras: dict[str, ResultCamera]
    frames: list[ResultFrame]
    hmm: Hmm
    notes: list[str]


class SyncCamera(_Open):
    offset_s: float | None = Field(description="the reference's time of this camera's first frame (s)")
    offset_frames: float | None = Field(description="the same in frames of this camera")
    fps: float | None
    uncertainty_s: float | None = Field(description="standard error of offset_s (s)")
    margin: float | None = Field(description="cost margin to the best fit at another part of the gait cycle")
    ambiguous: bool = Field(description="whole gait cycles could not be told apart (or the rate is too low)")


class SyncOut(_Open):
    """Offline synchronisation of recorded videos (docs/SYNC.md)."""

    reference: str
    cameras: dict[str, SyncCamera]
    notes: list[str]


class FeedbackOut(_Open):
    """Videos: each video segmented again with the model rendered from the first estimate as a
    foreground prior, and estimated again (docs/FORMATS.md, "feedback")."""

    done: bool = Field(description="the result is the second estimate's")
    priors: int | None = Field(None, description="frames given a prior (cameras whose estimate passed the trust "
                                                 "test)")
    changed_pixels: int | None = Field(None, description="silhouette pixels the second pass changed")
    note: str


class Result(_ResultBase):
    """A batch result: ``posecal estimate`` and ``GET /v1/jobs/{id}/result`` (docs/FORMATS.md, Result)."""

    rig: RigResult | None = None
    body: Body | None = None
    segments: list[SegmentOut] | None = None
    windows: list[WindowOut] | None = None
    sequence: dict[str, Any] | None = Field(None, description="posecal estimate: fps, image_size, frames")
    fps: float | None = Field(None, description="jobs: the input's frame rate")
    timing: dict[str, float] | None = None
    truth_cameras: dict[str, WindowViewpoint] | None = None
    refined: dict[str, Any] | None = None
    sync: SyncOut | None = Field(None, description="videos: each camera's time offset, found from the walk")
    feedback: FeedbackOut | None = Field(None, description="videos: the second segmentation with the model's "
                                                           "feedback (Izo-Grimson §7.1), when asked (default)")


class LiveWindow(_Open):
    seq: int
    first_index: int
    last_index: int
    frames: int
    cameras: list[str]
    missing: dict[str, list[int]] = Field(default_factory=dict, description=(
        "per camera of the window, the frame indices of the window without its message "
        "(cameras that are in every frame are left out)"))
    other_person: dict[str, list[int]] = Field(default_factory=dict, description=(
        "per camera, the frame indices left out of the estimate because its agent's track followed "
        "someone else there: its look back has since moved the track onto the walker (track_id, "
        "track_from)"))
    update: int = Field(0, description=(
        "the rig's count of results kept when this one was (first estimates and revisions): "
        "GET .../estimates?updated_since=N returns those after N"))
    revision: int = Field(0, description=(
        "0 for a window's first estimate; 1 or more when it was estimated again because a later move of "
        "an agent's look back said more of its frames were another person's (published again, and it "
        "replaces the first in the history)"))


class LivePerson(BaseModel):
    """The person's posture at the newest frame of a live rig's calibration."""

    frame_index: int = Field(description="the frame it belongs to (the rig lags the viewpoints by lag_windows)")
    joints3d: list[list[float]] = Field(
        description="13 joints (DESIGN order) x (x, y, z): person frame (x walking direction, y left, z up), "
                    "metres at the rig's stature, centred on the joints' centroid")


class LiveWindowPerson(LivePerson):
    """The person's posture as a live window carries it: the live rig's newest, which lags."""

    lag_windows: int = Field(description="windows between the calibration it comes from and this window")
    window_seq: int = Field(description="the window after which the rig was calibrated")


class LiveEstimate(_ResultBase):
    """A live window's result (docs/FORMATS.md, Live windows)."""

    rig: str = Field(description="the rig's name (not the rig object of a batch result)")
    window: LiveWindow
    smoothed: dict[str, dict[str, Any]]
    latency_ms: dict[str, float]
    published_ns: int
    person: LiveWindowPerson | None = Field(
        None, description="the person's posture from the live rig (GET /v1/rigs/{rig}/calibration), at its "
                          "newest frame with all 13 joints, lagging this window by lag_windows; absent while the "
                          "live rig is off or has no self-calibration")


class LiveCalibration(BaseModel):
    """A live rig's calibration (``GET /v1/rigs/{rig}/calibration``)."""

    rig: str = Field(description="the rig's name")
    source: Literal["self-calibration", "viewpoints"] = Field(
        description="viewpoints: too few postures yet, the rig is the viewpoints' (notes say why)")
    frames: int = Field(description="frames with measured postures (or keypoints) it was calibrated on")
    postures: Literal["mnbp", "keypoints"] = Field(
        "mnbp", description="what it was calibrated on: postures measured on the silhouettes (mNBP, a few "
                            "frames per window) or the keypoints of a pose detector that the agents send with "
                            "the silhouettes (every frame)")
    windows: int = Field(description="windows that gave postures since the start or the last camera move")
    window_seq: int = Field(description="the window after which it was calibrated")
    last_index: int = Field(description="that window's last frame index")
    lag_windows: int = Field(description="windows estimated since (the rig lags the viewpoints by this)")
    updated_ns: int
    calibration: RigResult = Field(description="the rig, as a batch result's rig")
    body: Body | None
    person: LivePerson | None = Field(None, description="the person's posture at the newest frame with "
                                                        "all 13 joints; null while the rig is the viewpoints'")
    notes: list[str]


class EstimatesOut(BaseModel):
    rig: str
    since: int
    estimates: list[LiveEstimate]
    next_since: int = Field(description="the highest window seq returned (or since): poll again with since=this")
    next_updated_since: int = Field(description=(
        "the highest window.update returned (or updated_since, else 0): poll again with updated_since=this "
        "to get revisions too"))


class ErrorOut(BaseModel):
    """Every error answer: FastAPI's ``{"detail": ...}``."""

    detail: str | list[dict[str, Any]] = Field(description="the reason, in words (a list for 422)")


_ERRORS = {
    400: "bad form fields or an input that cannot be read",
    401: "a bearer token is required (the service has api_token set) and was missing or wrong",
    403: "the bearer token lacks the scope this route needs (read: GET, submit: POST jobs, admin: the rest)",
    404: "no such job or rig, or nothing estimated yet",
    409: "the job is not in a state that allows this",
    413: "the upload exceeds a limit",
    415: "an upload of a type that is not accepted",
    422: "a parameter or an upload's content that fails validation",
    503: "the job store cannot be reached",
    507: "no space left to unpack the upload or to record the job",
}


def error_responses(*codes: int, examples: dict[int, str] | None = None) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the error statuses a route answers, each with an example body."""
    examples = examples or {}
    return {code: {"model": ErrorOut, "description": _ERRORS[code],
                   "content": {"application/json": {"example": {"detail": examples.get(code, _ERRORS[code])}}}}
            for code in codes}
