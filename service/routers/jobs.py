"""Batch jobs: submit (202), status, result, refined silhouettes, list, cancel, delete."""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Response, UploadFile, status
from fastapi.responses import FileResponse
from sqlalchemy.exc import OperationalError

from ..deps import MetricsDep, RunnerDep, SettingsDep, StoreDep, bearer_scheme
from ..exports import export_result
from ..intake import stage_keypoints
from ..jobs import ACTIVE, STATES
from ..schemas import JobList, JobOut, Result, error_responses, job_out
from ..worker import UploadError, stage_upload
from ._export import export_content, export_response

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], dependencies=[Depends(bearer_scheme)],
                   responses=error_responses(401, 403))


def _job_or_404(store: StoreDep, job_id: str):
    row = store.get(job_id)
    if row is None:
        raise HTTPException(404, f"unknown job {job_id!r}")
    return row


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobOut, responses=error_responses(
    400, 413, 415, 422, 503, 507, examples={
        400: "corrupt zip file: walk/c1/000010.png: Bad CRC-32",
        413: "c1/000003.png: the PNG header says 100000x100000, which exceeds the limit of 4096x4096",
        415: "expected one .zip sequence folder or videos (.mp4, .avi, ...), got ['walk.tar']",
        422: "rig.json: image_size must be two positive integers"}))
def submit_job(response: Response, store: StoreDep, runner: RunnerDep, settings: SettingsDep,
               metrics: MetricsDep,
               files: Annotated[list[UploadFile], File(description="one zipped sequence folder, "
                                                       "or one video per camera (<camera>.mp4)")],
               warmup: Annotated[int | None, Form(ge=1, description="videos: background frames "
                                                  "at the start (default: a quarter, at most 100)")] = None,
               refine: Annotated[bool, Form(description="also refine the silhouettes with model "
                                            "feedback (§7.1); download them from "
                                            "/v1/jobs/{id}/silhouettes")] = False,
               feedback: Annotated[Literal["on", "off"], Form(
                   description="videos: 'on' segments each video again with the model rendered from the first "
                   "estimate as a foreground prior (Izo-Grimson §7.1) and estimates again (about twice the "
                   "time; the result's feedback block); 'off' keeps the first estimate")] = "on",
               posture: Annotated[Literal["mnbp", "model"], Form(
                   description="frames[].joints2d: 'mnbp' = the person's 2D posture measured on "
                   "each silhouette (Wang-Leow §3; model_joints2d keeps the model's placement); "
                   "'model' = the gait model placed on the silhouette (faster)")] = "mnbp",
               height_m: Annotated[float, Form(ge=0.5, le=2.5, description="the walker's stature in "
                                               "metres: the scale of frames[].person_joints3d and "
                                               "body")] = 1.75,
               sync: Annotated[Literal["auto", "off"], Form(
                   description="videos: 'auto' finds each video's time offset from the walk and pairs "
                   "frames by time (cameras not started together, different frame rates; the offsets in "
                   "the result's sync block, docs/SYNC.md); 'off' pairs frames by index")] = "auto",
               keypoints: Annotated[UploadFile | None, File(
                   description="a zip of a pose detector's 2D keypoints of the same recording (OpenPose / "
                   "Pose2Sim <camera>_json folders, or one MMPose or MediaPipe JSON per camera; frame "
                   "numbers = the recording's frames, for videos each video's own, put on the common "
                   "timeline as its frames are): they calibrate the rig in place of the postures measured "
                   "on the silhouettes (docs/POSTURE.md)")] = None,
               ) -> JobOut:
    """Validate and stage the upload, queue the job; 4xx with the reason if the upload is bad."""
    job_id = uuid.uuid4().hex
    job_dir = settings.data_dir / job_id
    try:
        staged = stage_upload([(f.filename or "", f.file) for f in files], job_dir, settings.upload_limits())
        keypoints_dir = None
        if keypoints is not None:
            keypoints_dir = stage_keypoints(keypoints.file, job_dir, settings.upload_limits(), staged)
    except UploadError as exc:
        shutil.rmtree(job_dir, ignore_errors=True)
        metrics.uploads_rejected.labels(str(exc.status)).inc()
        raise HTTPException(exc.status, str(exc)) from None
    except BaseException:  # a bug (500): still nothing left behind
        shutil.rmtree(job_dir, ignore_errors=True)
        raise
    options: dict[str, Any] = {"cameras": staged.cameras, "n_frames": staged.n_frames,
                               "windows": settings.segment_options(), "posture": posture,
                               "height_m": height_m, "max_frames": settings.max_frames, "sync": sync,
                               "feedback": feedback}
    if staged.frame_counts:
        options["header_frames"] = staged.frame_counts
    if warmup is not None:
        options["warmup"] = warmup
    if refine:
        options.update(refine=True, refined_dir=str(job_dir))
    if keypoints_dir is not None:
        options["keypoints_dir"] = str(keypoints_dir)
    try:
        row = store.create(kind=staged.kind, input_dir=str(staged.path), options=options, job_id=job_id)
    except OperationalError as exc:  # the job store's disk is full (or the database is unreachable)
        shutil.rmtree(job_dir, ignore_errors=True)
        full = "full" in str(exc.orig).lower()
        metrics.uploads_rejected.labels("507" if full else "503").inc()
        raise HTTPException(507 if full else 503, "no space left to record the job" if full
                            else "the job store cannot be reached") from None
    except BaseException:
        shutil.rmtree(job_dir, ignore_errors=True)
        raise
    metrics.jobs_submitted.inc()
    runner.wake()
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return job_out(row)


@router.get("", response_model=JobList)
def list_jobs(store: StoreDep,
              state: Annotated[str | None, Query(pattern="^(" + "|".join(STATES) + ")$")] = None,
              limit: Annotated[int, Query(ge=1, le=1000)] = 100,
              offset: Annotated[int, Query(ge=0)] = 0) -> JobList:
    """Jobs, newest first, optionally of one state."""
    return JobList(jobs=[job_out(r) for r in store.list(state=state, limit=limit, offset=offset)],
                   counts=store.counts())


@router.get("/{job_id}", response_model=JobOut, responses=error_responses(404))
def get_job(job_id: str, store: StoreDep) -> JobOut:
    return job_out(_job_or_404(store, job_id))


ResultFormat = Literal["json", "trc", "bvh", "csv", "toml", "yaml"]


@router.get("/{job_id}/result", response_model=None, responses={
    200: {"model": Result, "content": export_content("trc", "bvh", "csv", "toml", "yaml")}, **error_responses(
        400, 404, 409, examples={400: "format 'toml': the rig has no metric cameras (focal lengths, centres in "
                                      "metres): its source is 'viewpoints', without pinhole cameras (notes say why)",
                                 409: "job 3f2a... is running"})})
def get_result(job_id: str, store: StoreDep, format: Annotated[ResultFormat, Query(
        description="json: the result (docs/FORMATS.md); trc, bvh, csv: its 3D joints (person_joints3d when the "
                    "rig was self-calibrated, else joints3d; docs/FORMATS.md, \"Exports\"); toml (Pose2Sim / "
                    "anipose), yaml (OpenCV): its rig's pinhole cameras, when it has them (else 400)")] = "json",
               ) -> dict[str, Any] | Response:
    """The result (docs/FORMATS.md) of a finished job, or an export of it; 409 while it is not done,
    400 for a format the result cannot give (with the reason)."""
    row = _job_or_404(store, job_id)
    if row.state != "done":
        detail = f"job {job_id} is {row.state}" + (f": {row.error}" if row.error else "")
        raise HTTPException(409, detail)
    result = store.result(job_id)
    if result is None:
        raise HTTPException(409, f"job {job_id} has no result")
    if format == "json":
        return result
    name = f"{job_id}.{format}"
    return export_response(lambda: export_result(result, format, name), format, name)


@router.get("/{job_id}/silhouettes", response_class=FileResponse,
            responses={200: {"content": {"application/zip": {}}}, **error_responses(404, 409)})
def get_silhouettes(job_id: str, store: StoreDep) -> FileResponse:
    """The refined silhouettes of a job submitted with ``refine=true``, as a zipped
    sequence folder; 404 if it was not asked for, 409 while the job is not done."""
    row = _job_or_404(store, job_id)
    refined_dir = (row.options or {}).get("refined_dir")
    if not refined_dir:
        raise HTTPException(404, f"job {job_id} was not submitted with refine=true")
    if row.state != "done":
        raise HTTPException(409, f"job {job_id} is {row.state}" + (f": {row.error}" if row.error else ""))
    path = Path(refined_dir) / "silhouettes.zip"
    if not path.is_file():
        raise HTTPException(409, f"job {job_id} has no refined silhouettes")
    return FileResponse(path, media_type="application/zip", filename=f"{job_id}-silhouettes.zip")


@router.post("/{job_id}/cancel", response_model=JobOut, responses=error_responses(404, 409))
def cancel_job(job_id: str, store: StoreDep) -> JobOut:
    """Cancel a queued or running job; 409 if it already ended."""
    row = _job_or_404(store, job_id)
    if row.state not in ACTIVE:
        raise HTTPException(409, f"job {job_id} already ended ({row.state})")
    return job_out(store.cancel(job_id))


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses(404))
def delete_job(job_id: str, store: StoreDep, settings: SettingsDep) -> Response:
    """Forget a job and its files (a running one is cancelled first)."""
    _job_or_404(store, job_id)
    store.cancel(job_id)
    store.delete(job_id)
    shutil.rmtree(settings.data_dir / job_id, ignore_errors=True)
    return Response(status_code=status.HTTP_204_NO_CONTENT)
