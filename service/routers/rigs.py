"""Live rigs: ``/v1/rigs``, one rig, its latest estimate and estimates since a window.

With several replicas each answers for the rigs it estimates; asked for another
replica's rig it answers 404 naming that replica (``GET /v1/replicas`` lists them)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, HTTPException, Query, Response

from ..deps import LiveDep, RuntimeDep, bearer_scheme
from ..exports import export_calibration
from ..schemas import EstimatesOut, LiveCalibration, LiveEstimate, RigList, RigOut, error_responses
from ._export import export_content, export_response

router = APIRouter(prefix="/v1/rigs", tags=["rigs"], dependencies=[Depends(bearer_scheme)],
                   responses=error_responses(401, 403))


def _unknown_rig(live: LiveDep, rig: str) -> HTTPException:
    """404: the rig is estimated by another replica (named), or no silhouettes came for it."""
    owner = live.estimated_by(rig)
    if owner is not None:
        return HTTPException(404, f"rig {rig!r} is estimated by replica {owner!r}")
    return HTTPException(404, f"unknown rig {rig!r}: no silhouettes received for it")


def _rig_or_404(live: LiveDep, rig: str) -> None:
    if not live.has_rig(rig):
        raise _unknown_rig(live, rig)


@router.get("", response_model=RigList)
def list_rigs(rt: RuntimeDep) -> RigList:
    """The rigs this replica estimates."""
    live = rt.live
    if live is None:
        return RigList(live=False, rigs=[])
    return RigList(live=True, rigs=[RigOut(**s) for n in live.rig_names() if (s := live.summary(n))])


@router.get("/{rig}", response_model=RigOut,
            responses=error_responses(404, examples={404: "rig 'lab' is estimated by replica 'b'"}))
def get_rig(rig: str, live: LiveDep) -> RigOut:
    """The rig's summary, if this replica estimates it (else 404 naming the replica that does)."""
    summary = live.summary(rig)
    if summary is None:
        raise _unknown_rig(live, rig)
    return RigOut(**summary)


@router.get("/{rig}/estimate", responses={200: {"model": LiveEstimate}, **error_responses(
    404, examples={404: "rig 'lab' has no estimated window yet"})})
def latest_estimate(rig: str, live: LiveDep) -> dict[str, Any]:
    """The latest window's result (the docs/FORMATS.md result plus rig, window, smoothed, latency_ms)."""
    _rig_or_404(live, rig)
    latest = live.latest(rig)
    if latest is None:
        raise HTTPException(404, f"rig {rig!r} has no estimated window yet")
    return latest


@router.get("/{rig}/estimates", responses={200: {"model": EstimatesOut}, **error_responses(
    404, 422, examples={404: "unknown rig 'lab': no silhouettes received for it"})})
def estimates_since(rig: str, live: LiveDep,
                    since: int = Query(0, ge=0, description="return windows with seq > since"),
                    limit: int = Query(100, ge=1, le=1000),
                    updated_since: int | None = Query(None, ge=0, description=(
                        "instead of since: return the results kept after this window.update, first "
                        "estimates and revisions alike, in that order"))) -> dict[str, Any]:
    """Recent results with window ``seq`` greater than ``since``, oldest first; or, with
    ``updated_since``, every result kept since (a window estimated again after a later move of an
    agent's look back comes again, with ``window.revision`` one more)."""
    _rig_or_404(live, rig)
    items = live.since(rig, since, limit, updated_since=updated_since) or []
    return {"rig": rig, "since": since, "estimates": items,
            "next_since": max([since, *(e["window"]["seq"] for e in items)]),
            "next_updated_since": max([updated_since or 0, *(e["window"]["update"] for e in items)])}


@router.get("/{rig}/calibration", response_model=LiveCalibration, responses={
    200: {"content": export_content("toml", "yaml")}, **error_responses(
        400, 404, examples={
            400: "format 'toml': the rig has no metric cameras (focal lengths, centres in metres): its source is "
                 "'viewpoints', without pinhole cameras (notes say why)",
            404: "rig 'lab' has no calibration yet: it needs postures on 8 frames seen by two cameras"})})
def live_calibration(rig: str, live: LiveDep, format: Annotated[Literal["json", "toml", "yaml"], Query(
        description="json: the calibration below; toml (Pose2Sim / anipose), yaml (OpenCV): its pinhole cameras "
                    "in the reference camera's frame (docs/FORMATS.md, \"Exports\"), when it has them "
                    "(else 400)")] = "json") -> dict[str, Any] | Response:
    """The rig calibrated from the live windows so far (Wang–Leow §3-4 on a few frames per window).

    Cameras are taken as fixed: the rig is solved over the postures of recent
    windows (at most ``max_frames`` frames), recalibrated every few windows, and
    restarted when a camera moves. ``lag_windows`` says how far it is behind the
    latest estimate. ``format=toml|yaml``: the same rig as a calibration file
    (400 with the reason when it has no pinhole cameras)."""
    _rig_or_404(live, rig)
    cal = live.calibration(rig)
    if cal is None:
        raise HTTPException(404, f"rig {rig!r} has no calibration yet: it needs postures on 8 frames seen by "
                                 "two cameras (live_rig off, or too few windows since the start or a camera move)")
    if format == "json":
        return cal
    return export_response(lambda: export_calibration(cal, format), format, f"{rig}-calibration.{format}")
