"""Response models of the REST API (storage rows and live state are converted here)."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, Field

from .jobs import JobRow

__all__ = ["Health", "JobList", "JobOut", "RigList", "RigOut", "job_out"]

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
    last_index: int
    last_seen_ns: int
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


class FrameCounts(BaseModel):
    late: int
    duplicate: int
    missing: int = Field(description="camera frames absent when a frame set closed")
    restarts: int = Field(description="agent restarts (new epochs)")
    gaps: int = Field(description="frame index jumps that restarted the window")


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
