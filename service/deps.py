"""Shared dependencies and their typed aliases (FastAPI "Bigger Applications")."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPBearer

from .jobs import JobStore
from .live import LiveService
from .metrics import Metrics
from .runner import JobRunner
from .runtime import Runtime
from .settings import Settings, get_settings

__all__ = ["LiveDep", "MetricsDep", "RunnerDep", "RuntimeDep", "SettingsDep", "StoreDep", "bearer_scheme"]


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


def get_store(request: Request) -> JobStore:
    return get_runtime(request).store


def get_runner(request: Request) -> JobRunner:
    return get_runtime(request).runner


def get_metrics(request: Request) -> Metrics:
    return get_runtime(request).metrics


def get_live(request: Request) -> LiveService:
    live = get_runtime(request).live
    if live is None:
        raise HTTPException(503, "live estimation is disabled on this server (POSECAL_LIVE=false)")
    return live


# REST access is enforced by service.auth.BearerAuthMiddleware (from the headers, before a
# body is read); routers declare this scheme so that OpenAPI shows it.
bearer_scheme = HTTPBearer(auto_error=False, description="when the service has api_token or api_token_file "
                           "set: every /v1 route (and /metrics, unless metrics_open) needs "
                           "'Authorization: Bearer <token>', else 401; a token without the route's "
                           "scope (read: GET, submit: POST /v1/jobs, admin: cancel, delete) gets 403")


SettingsDep = Annotated[Settings, Depends(get_settings)]
RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
StoreDep = Annotated[JobStore, Depends(get_store)]
RunnerDep = Annotated[JobRunner, Depends(get_runner)]
MetricsDep = Annotated[Metrics, Depends(get_metrics)]
LiveDep = Annotated[LiveService, Depends(get_live)]
