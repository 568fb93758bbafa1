"""``/healthz`` and ``/metrics`` (Prometheus text format)."""

from __future__ import annotations

from fastapi import APIRouter, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ..deps import MetricsDep, RuntimeDep, SettingsDep, StoreDep
from ..schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz(rt: RuntimeDep, settings: SettingsDep, store: StoreDep) -> Health:
    """Liveness and a short inventory: live on/off, endpoints, model, jobs per state."""
    return Health(status="ok", live=rt.live is not None,
                  zenoh_listen=list(settings.zenoh_listen) if settings.live else [],
                  rerun=settings.rerun, model=str(rt.model_path), jobs=store.counts())


@router.get("/metrics", response_class=Response)
def metrics(m: MetricsDep) -> Response:
    return Response(m.render(), media_type=CONTENT_TYPE_LATEST)
