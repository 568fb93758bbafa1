"""Live rigs: ``/v1/rigs``, one rig, its latest estimate and estimates since a window."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException, Query

from ..deps import LiveDep, RuntimeDep
from ..schemas import RigList, RigOut

router = APIRouter(prefix="/v1/rigs", tags=["rigs"])


def _unknown_rig(rig: str) -> HTTPException:
    return HTTPException(404, f"unknown rig {rig!r}: no silhouettes received for it")


def _rig_or_404(live: LiveDep, rig: str) -> None:
    if not live.has_rig(rig):
        raise _unknown_rig(rig)


@router.get("", response_model=RigList)
def list_rigs(rt: RuntimeDep) -> RigList:
    live = rt.live
    if live is None:
        return RigList(live=False, rigs=[])
    return RigList(live=True, rigs=[RigOut(**s) for n in live.rig_names() if (s := live.summary(n))])


@router.get("/{rig}", response_model=RigOut)
def get_rig(rig: str, live: LiveDep) -> RigOut:
    summary = live.summary(rig)
    if summary is None:
        raise _unknown_rig(rig)
    return RigOut(**summary)


@router.get("/{rig}/estimate")
def latest_estimate(rig: str, live: LiveDep) -> dict[str, Any]:
    """The latest window's result (the docs/FORMATS.md result plus rig, window, smoothed, latency_ms)."""
    _rig_or_404(live, rig)
    latest = live.latest(rig)
    if latest is None:
        raise HTTPException(404, f"rig {rig!r} has no estimated window yet")
    return latest


@router.get("/{rig}/estimates")
def estimates_since(rig: str, live: LiveDep,
                    since: int = Query(0, ge=0, description="return windows with seq > since"),
                    limit: int = Query(100, ge=1, le=1000)) -> dict[str, Any]:
    """Recent results with window ``seq`` greater than ``since``, oldest first."""
    _rig_or_404(live, rig)
    items = live.since(rig, since, limit) or []
    return {"rig": rig, "since": since, "estimates": items,
            "next_since": items[-1]["window"]["seq"] if items else since}
