"""The FastAPI application: routers and the lifespan, nothing else.

``uvicorn service.app:app`` (or ``posecal serve``) runs it; configuration comes
from :func:`service.settings.get_settings`, which tests replace through
``app.dependency_overrides``.
"""

from __future__ import annotations

from contextlib import asynccontextmanager

from fastapi import FastAPI

from .auth import BearerAuthMiddleware
from .limits import UploadLimitMiddleware
from .routers import health, jobs, replicas, rigs
from .runtime import Runtime
from .settings import get_settings

__all__ = ["app", "create_app"]


@asynccontextmanager
async def lifespan(app: FastAPI):
    settings = app.dependency_overrides.get(get_settings, get_settings)()
    app.state.settings = settings
    app.state.runtime = await Runtime.start(settings)
    try:
        yield
    finally:
        await app.state.runtime.stop()


def create_app() -> FastAPI:
    app = FastAPI(title="posecal", summary="Walking pose and camera viewpoints from uncalibrated cameras",
                  lifespan=lifespan)
    app.add_middleware(UploadLimitMiddleware, prefix="/v1/jobs")
    app.add_middleware(BearerAuthMiddleware, prefix="/v1")  # added last: runs first
    app.include_router(health.router)
    app.include_router(jobs.router)
    app.include_router(rigs.router)
    app.include_router(replicas.router)
    return app


app = create_app()
