"""``/healthz`` (always open: liveness probes) and ``/metrics`` (Prometheus text format; behind
the API token when one is set, unless ``metrics_open``)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, Response
from prometheus_client import CONTENT_TYPE_LATEST

from ..deps import MetricsDep, RuntimeDep, SettingsDep, StoreDep, bearer_scheme
from ..schemas import Health, error_responses

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz(rt: RuntimeDep, settings: SettingsDep, store: StoreDep) -> Health:
    """Liveness and a short inventory: live on/off, endpoints, model, jobs per state."""
    return Health(status="ok", live=rt.live is not None,
                  zenoh_listen=list(settings.zenoh_listen) if settings.live else [],
                  rerun=settings.rerun, model=str(rt.model_path), jobs=store.counts())


@router.get("/metrics", response_class=Response, dependencies=[Depends(bearer_scheme)],
            responses=error_responses(401, 403))
def metrics(m: MetricsDep) -> Response:
    return Response(m.render(), media_type=CONTENT_TYPE_LATEST)
