"""Service configuration: one typed settings object, read from ``POSECAL_*`` variables.

:func:`get_settings` is the FastAPI dependency (cached); tests and ``posecal
serve`` replace it through ``app.dependency_overrides`` or by building the app
with explicit settings (:func:`service.app.create_app`).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

__all__ = ["Settings", "get_settings", "parse_rerun_sink"]

DEFAULT_ZENOH_LISTEN = "tcp/127.0.0.1:7447"


def parse_rerun_sink(spec: str | None) -> tuple[str, str | int] | None:
    """Parse ``save:PATH``, ``serve[:PORT]`` or ``connect[:URL]``; None/empty/"off" = no Rerun."""
    if spec is None or spec in ("", "off", "none"):
        return None
    kind, _, target = spec.partition(":")
    if kind == "save":
        if not target:
            raise ValueError("rerun sink save:PATH needs a path")
        return "save", target
    if kind == "serve":
        try:
            port = int(target) if target else 9876
        except ValueError:
            raise ValueError(f"rerun sink serve:PORT needs an integer port, got {target!r}") from None
        if not 0 <= port < 65536:
            raise ValueError(f"rerun port out of range: {port}")
        return "serve", port
    if kind == "connect":
        return "connect", target or "rerun+http://127.0.0.1:9876/proxy"
    raise ValueError(f"rerun sink must be save:PATH, serve[:PORT] or connect[:URL], got {spec!r}")


class Settings(BaseSettings):
    """Everything the service reads from its environment (env prefix ``POSECAL_``)."""

    model_config = SettingsConfigDict(env_prefix="POSECAL_", frozen=True)

    # storage
    db: str = Field("posecal.db", description="SQLite file path, or a SQLAlchemy URL "
                    "(e.g. postgresql+psycopg://user@host/posecal)")
    data_dir: Path = Field(Path("posecal-data"), description="uploaded job inputs live here")
    # model
    model_path: Path | None = Field(None, description="appearance model (.npz); default: the "
                                    "cached default model, built on first use")
    cache_dir: Path | None = Field(None, description="model cache (default: $POSECAL_CACHE or ~/.cache/posecal)")
    # jobs
    job_workers: int = Field(1, ge=0, description="processes that run jobs (0 = jobs stay queued)")
    upload_limit_mb: float = Field(200.0, gt=0, description="largest accepted upload (413 above)")
    max_frames: int = Field(5000, ge=1, description="most frames per camera in one job")
    # live
    live: bool = Field(True, description="subscribe to silhouettes and estimate windows")
    live_workers: int = Field(1, ge=1, description="processes that estimate live windows")
    window_length: int = Field(20, ge=4, description="frames per window (about one gait cycle; "
                               "live windows and the windows of batch jobs)")
    window_hop: int = Field(10, ge=1, description="frames between window starts")
    sync_tolerance_ms: float = Field(20.0, gt=0, description="capture times closer than this "
                                     "are the same frame (cameras synchronised by time)")
    max_wait_ms: float = Field(120.0, gt=0, description="how long a frame waits for missing cameras")
    camera_timeout_s: float = Field(3.0, gt=0, description="a camera silent this long is no "
                                    "longer waited for")
    min_present: float = Field(0.5, ge=0, le=1, description="fraction of a window's frames that "
                               "must hold a silhouette for it to be estimated")
    history: int = Field(500, ge=1, description="recent window results kept per rig")
    queue_limit: int = Field(8, ge=1, description="windows waiting for estimation before the "
                             "oldest is dropped")
    change_threshold_deg: float = Field(30.0, gt=0, description="a window this far from the "
                                        "smoothed viewpoint is an outlier ...")
    change_windows: int = Field(3, ge=1, description="... and this many consecutive agreeing "
                                "outliers mean the camera moved or the walker turned (a batch "
                                "job starts a new segment there)")
    # feedback (§7.1)
    feedback: bool = Field(True, description="publish silhouette priors to the segmenters "
                           "after each live window (in a process of its own)")
    feedback_ahead: int = Field(20, ge=1, description="frames predicted per window, after "
                                "those captured while the priors are made: window_hop plus "
                                "room for late priors")
    # zenoh
    zenoh_mode: str = Field("peer", pattern="^(peer|client|router)$")
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_listen: list[str] = Field(default_factory=lambda: [DEFAULT_ZENOH_LISTEN])
    zenoh_config: Path | None = Field(None, description="zenoh JSON5 config file (the fields above override it)")
    zenoh_multicast: bool = Field(False, description="multicast scouting (off: on-host only)")
    # rerun
    rerun: str | None = Field(None, description="save:PATH | serve[:PORT] | connect[:URL]")
    rerun_jobs: bool = Field(True, description="also log batch jobs to Rerun")

    def segment_options(self) -> dict[str, float | int]:
        """How batch jobs cut a recording (:func:`estimator.windows.segment_walk`): as live windows are."""
        return {"length": self.window_length, "hop": self.window_hop,
                "threshold_deg": self.change_threshold_deg, "confirm": self.change_windows}

    @field_validator("rerun")
    @classmethod
    def _check_rerun(cls, value: str | None) -> str | None:
        parse_rerun_sink(value)
        return value

    @property
    def db_url(self) -> str:
        """A SQLAlchemy URL: ``db`` as given if it has a scheme, else a SQLite file."""
        if "://" in self.db:
            return self.db
        return f"sqlite:///{Path(self.db).expanduser().resolve()}"

    @property
    def upload_limit_bytes(self) -> int:
        return int(self.upload_limit_mb * 1024 * 1024)

    @property
    def rerun_sink(self) -> tuple[str, str | int] | None:
        return parse_rerun_sink(self.rerun)


@lru_cache
def get_settings() -> Settings:
    """The process's settings (read once from the environment)."""
    return Settings()
