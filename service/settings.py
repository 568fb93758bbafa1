"""Service configuration: one typed settings object, read from ``POSECAL_*`` variables.

:func:`get_settings` is the FastAPI dependency (cached); tests and ``posecal
serve`` replace it through ``app.dependency_overrides`` or by building the app
with explicit settings (:func:`service.app.create_app`).
"""

from __future__ import annotations

import os
import socket
from functools import lru_cache
from pathlib import Path

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from capture.zconfig import ZenohAccess

from .auth import ApiToken, parse_token_line
from .limits import UploadLimits

__all__ = ["Settings", "data_home", "get_settings", "parse_rerun_sink"]

DEFAULT_ZENOH_LISTEN = "tcp/127.0.0.1:7447"


def xdg_dir(own: str, xdg: str, default: str) -> Path:
    """``$<own>`` if set, else ``$<xdg>/posecal``, else ``~/<default>/posecal`` (the XDG base
    directory specification: a relative ``$<xdg>`` is ignored); read at call time."""
    if os.environ.get(own):
        return Path(os.environ[own]).expanduser()
    base = os.environ.get(xdg, "")
    return (Path(base) if base and os.path.isabs(base) else Path.home() / default) / "posecal"


def data_home() -> Path:
    """Where the service keeps its state unless told otherwise: ``$POSECAL_DATA``, else
    ``$XDG_DATA_HOME/posecal``, else ``~/.local/share/posecal``. Never the working directory."""
    return xdg_dir("POSECAL_DATA", "XDG_DATA_HOME", ".local/share")


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

    # storage (default: under data_home(), never the working directory)
    db: str = Field(default_factory=lambda: str(data_home() / "posecal.db"),
                    description="SQLite file path, or a SQLAlchemy URL (e.g. "
                    "postgresql+psycopg://user@host/posecal); default: <data home>/posecal.db")
    data_dir: Path = Field(default_factory=lambda: data_home() / "jobs",
                           description="uploaded job inputs live here; default: <data home>/jobs")
    # model
    model_path: Path | None = Field(None, description="appearance model (.npz); default: the "
                                    "cached default model, built on first use")
    cache_dir: Path | None = Field(None, description="model cache (default: $POSECAL_CACHE or ~/.cache/posecal)")
    # replicas (docs/SCALING.md): several services on one database and one Zenoh network
    replica_id: str = Field(default_factory=lambda: socket.gethostname() or "posecal",
                            pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,62}$",
                            description="this service's name among its replicas: the owner of the "
                            "jobs it runs and of the live rigs it estimates; stable across restarts, "
                            "unique among running replicas (default: the host name)")
    replicas: bool = Field(True, description="share the live rigs with the other replicas on the Zenoh "
                           "network (liveliness tokens, rendezvous hashing; docs/SERVICE.md, \"Several "
                           "replicas\"): each rig is estimated by exactly one; a replica alone estimates every rig")
    replica_lease_s: float = Field(2.0, ge=0.5, le=60.0, description="Zenoh transport lease the service "
                                   "announces: a replica that vanishes without closing its links (host "
                                   "lost) is seen gone this long after its last keep-alive (bounds failover)")
    # jobs
    job_workers: int = Field(1, ge=0, description="processes that run jobs (0 = jobs stay queued)")
    max_attempts: int = Field(3, ge=1, description="runs of a job that a stop or crash may "
                              "interrupt; a job interrupted this often fails instead of being re-queued")
    job_lease_s: float = Field(30.0, gt=0, description="a running job whose replica has not renewed "
                               "its lease for this long (renewed every third of it) is re-queued by "
                               "any replica: the replica died or lost the database")
    upload_limit_mb: float = Field(200.0, gt=0, description="largest accepted upload (413 above)")
    max_frames: int = Field(5000, ge=1, description="most frames per camera in one job (a PNG "
                            "named 5000.png or above, a video whose header counts more: 413)")
    unpacked_limit_mb: float = Field(800.0, gt=0, description="a zip's members summed, as declared "
                                     "and as extracted (413 above)")
    max_decoded_mb: float = Field(1024.0, gt=0, description="PNG pixels of an uploaded sequence "
                                  "summed, read from their headers before decoding (413 above)")
    max_image_side: int = Field(4096, ge=16, description="largest width or height of a frame: "
                                "uploaded PNGs, videos and rig.json's image_size (413 above)")
    max_image_pixels: int = Field(4096 * 4096, ge=256, description="largest width x height of "
                                  "the same (413 above)")
    max_cameras: int = Field(16, ge=1, description="cameras per upload, and per live rig (more "
                             "are refused and counted)")
    # live
    live: bool = Field(True, description="subscribe to silhouettes and estimate windows")
    live_workers: int = Field(default_factory=lambda: min(2, os.cpu_count() or 1), ge=1,
                              description="processes that estimate live windows, a window's cameras split over "
                              "them, each camera always in the same one (default: 2, or 1 on one core; "
                              "~175 MB each; docs/SCALING.md)")
    window_length: int = Field(20, ge=4, description="frames per window (about one gait cycle; "
                               "live windows and the windows of batch jobs)")
    window_hop: int = Field(10, ge=1, description="frames between window starts")
    warm_every: int = Field(3, ge=0, description="live: every this many frames, the frames of the "
                            "next window so far are registered and matched by the processes that "
                            "will estimate it, so that a closed window waits on its last frames only "
                            "(0: at the window's close, all at once)")
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
                                "job starts a new segment there); live, not while the smoothed "
                                "viewpoint rests on fewer windows (a bad start, not a move)")
    fold_windows: int = Field(2, ge=0, description="live: a camera whose last this many windows agreed "
                              "with its smoothed viewpoint keeps that side of the ahead/behind fold in a window "
                              "that finds it on the other, unless the other cameras' phase says otherwise "
                              "(0: off; docs/ROBUSTNESS.md, \"The side the earlier windows found\")")
    # live: what a message must be to be believed (docs/SERVICE.md, "Limits and refusals")
    max_rigs: int = Field(32, ge=1, description="live rigs kept; a new one beyond this replaces "
                          "the longest-silent rig that is silent, else it is refused and counted")
    rig_expiry_s: float = Field(600.0, gt=0, description="a rig (or a camera) silent this long "
                                "is forgotten, with its metrics")
    max_clock_ahead_s: float = Field(30.0, gt=0, description="a silhouette whose epoch_ns or "
                                     "capture_ns is further ahead of the receiver's clock is "
                                     "dropped and counted")
    max_index_ahead: int = Field(150, ge=1, description="a silhouette whose frame_index is further "
                                 "ahead of its rig's (sync=index) or its camera's latest is "
                                 "dropped and counted, until a few in a row agree")
    # feedback (§7.1)
    feedback: bool = Field(True, description="publish silhouette priors to the segmenters "
                           "after each live window (in a process of its own)")
    feedback_ahead: int = Field(20, ge=1, description="frames predicted per window, after "
                                "those captured while the priors are made: window_hop plus "
                                "room for late priors")
    # the live rig (Wang-Leow §3-4 over live windows)
    live_rig: bool = Field(True, description="calibrate each live rig from the 2D postures (mNBP) of a few "
                           "frames per window, in a low-priority process of its own: GET "
                           "/v1/rigs/{rig}/calibration")
    live_rig_frames: int = Field(2, ge=1, description="frames per window whose postures are measured "
                                 "(mNBP costs about 60 ms per frame and camera)")
    live_rig_every: int = Field(3, ge=1, description="recalibrate after this many windows with new postures")
    live_rig_height_m: float = Field(1.75, ge=0.5, le=2.5, description="the walkers' stature, for the "
                                     "metric scale of the live rig and body")
    # zenoh
    zenoh_mode: str = Field("peer", pattern="^(peer|client|router)$")
    zenoh_connect: list[str] = Field(default_factory=list)
    zenoh_listen: list[str] = Field(default_factory=lambda: [DEFAULT_ZENOH_LISTEN])
    zenoh_config: Path | None = Field(None, description="zenoh JSON5 config file (the fields above override it)")
    zenoh_multicast: bool = Field(False, description="multicast scouting (off: on-host only)")
    zenoh_access: ZenohAccess = Field(default_factory=ZenohAccess, description="user/password, TLS "
                                      "and access rules (POSECAL_ZENOH_USER, ..._TLS_CERTIFICATE, "
                                      "..._AGENTS, ...: capture.zconfig)")
    # REST access (docs/SERVICE.md, "Access")
    api_token: SecretStr | None = Field(None, description="bearer token with every scope: every /v1 "
                                        "route needs 'Authorization: Bearer <token>' (401 otherwise)")
    api_token_file: Path | None = Field(None, description="a file of bearer tokens, one per line "
                                        "('#' comments): 'TOKEN' (every scope) or 'TOKEN SCOPE[,SCOPE]' "
                                        "with read (GET), submit (POST jobs, and read), admin (cancel, "
                                        "delete, everything); a missing scope is 403")
    metrics_open: bool = Field(False, description="serve /metrics without a token even when tokens "
                               "are set (/healthz is always open)")
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

    def api_tokens(self) -> tuple[ApiToken, ...]:
        """The accepted bearer tokens and their scopes (empty: REST is open); ValueError for
        an unreadable or empty token file, a short token or an unknown scope."""
        tokens = [] if self.api_token is None else [ApiToken(self.api_token.get_secret_value().strip().encode())]
        if self.api_token_file is not None:
            try:
                lines = Path(self.api_token_file).expanduser().read_text().splitlines()
            except OSError as exc:
                raise ValueError(f"cannot read the API token file {self.api_token_file}: {exc}") from None
            found = []
            for number, line in enumerate(lines, 1):
                if line.strip() and not line.lstrip().startswith("#"):
                    try:
                        found.append(parse_token_line(line))
                    except ValueError as exc:
                        raise ValueError(f"{self.api_token_file} line {number}: {exc}") from None
            if not found:
                raise ValueError(f"the API token file {self.api_token_file} holds no token")
            tokens += found
        if any(len(t.secret) < 16 for t in tokens):
            raise ValueError("API tokens must be at least 16 characters (e.g. `openssl rand -hex 32`)")
        return tuple(tokens)

    @property
    def upload_limit_bytes(self) -> int:
        return int(self.upload_limit_mb * 1024 * 1024)

    def upload_limits(self) -> UploadLimits:
        """What the intake checks before it spends (:class:`service.limits.UploadLimits`)."""
        mb = 1024 * 1024
        return UploadLimits(body_bytes=self.upload_limit_bytes,
                            unpacked_bytes=int(self.unpacked_limit_mb * mb), max_frames=self.max_frames,
                            max_cameras=self.max_cameras, max_image_side=self.max_image_side,
                            max_image_pixels=self.max_image_pixels,
                            decoded_bytes=int(self.max_decoded_mb * mb))

    @property
    def rerun_sink(self) -> tuple[str, str | int] | None:
        return parse_rerun_sink(self.rerun)


@lru_cache
def get_settings() -> Settings:
    """The process's settings (read once from the environment)."""
    return Settings()
