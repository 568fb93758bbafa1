"""Helpers shared by the service tests: a small appearance model, a real uvicorn
server on 127.0.0.1 in a thread, free ports, synthetic sequence zips.

Imported by the ``test_service_*`` modules (``tests/conftest.py`` is not ours).
"""

from __future__ import annotations

import io
import os
import tempfile
import time
import zipfile
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import httpx

from service.server import BackgroundServer, free_port
from service.settings import Settings

SMALL_GRID = {"azimuth_step_deg": 15.0, "elevations_deg": (-10.0, 10.0, 30.0)}


def small_model_path() -> Path:
    """A 40-cluster model (15 deg azimuth steps, 3 elevations), built once and kept in the
    temp directory across sessions and test workers (~10-30 s to build): the default model's
    cache (:func:`estimator.appearance.default_model`, which builds under a file lock) with
    a smaller grid."""
    from estimator import appearance, examples

    key = {"source": "tests/conftest_service.small_model_path", "grid": SMALL_GRID,
           "render_version": getattr(examples, "RENDER_VERSION", "")}
    cache = Path(tempfile.gettempdir()) / "posecal-test-models"
    path = cache / appearance.model_filename({**key, "n_clusters": 40, "seed": 0})
    if not path.exists():
        appearance.default_model(cache, key=key, n_clusters=40, rng=0,
                                 make_examples=lambda: examples.render_examples(examples.ExampleGrid(**SMALL_GRID)))
    return path


def make_settings(tmp: Path, **overrides) -> Settings:
    """Settings for a test server: files under ``tmp``, Zenoh on a free loopback port."""
    base = dict(db=str(tmp / "jobs.db"), data_dir=tmp / "data", model_path=small_model_path(),
                live=False, zenoh_listen=[f"tcp/127.0.0.1:{free_port()}"], job_workers=1)
    base.update(overrides)
    return Settings(**base)


class ServerThread(BackgroundServer):
    """The app with ``settings`` under uvicorn on 127.0.0.1 in a thread, plus an httpx client."""

    def __init__(self, settings: Settings) -> None:
        super().__init__(settings, start_timeout=60.0)
        self.client = httpx.Client(base_url=self.url, timeout=30.0)

    def rig(self, name: str) -> dict:
        """``GET /v1/rigs/{name}``, or ``{}`` while the service has not heard of the rig (404):
        a poll that starts before the first silhouette arrives waits instead of failing."""
        r = self.client.get(f"/v1/rigs/{name}")
        if r.status_code == 404:
            return {}
        r.raise_for_status()
        return r.json()

    def stop(self) -> None:
        self.client.close()
        super().stop()


def wait_for(predicate, *, timeout: float, interval: float = 0.05, what: str = "condition"):
    """Poll until ``predicate()`` is truthy; return its value or fail after ``timeout`` s."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(interval)


def wait_for_server(proc, url: str, *, timeout: float = 120.0) -> None:
    """Wait until the ``posecal serve`` process ``proc`` answers ``/healthz`` at ``url``; fail at
    once if it exits."""
    def up() -> bool:
        if proc.poll() is not None:
            raise AssertionError(f"posecal serve exited with {proc.returncode}")
        try:
            return httpx.get(f"{url}/healthz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    wait_for(up, timeout=timeout, interval=0.2, what="posecal serve to answer")


def write_walk(path: Path, *, n_frames: int, seed: int, image_size: tuple[int, int] = (640, 480)) -> Path:
    """A synthetic 2-camera walk (cameras at 60 and 150 deg azimuth, 10 deg elevation) written
    as a sequence folder at ``path``; returns ``path``."""
    from estimator.sequence import write_sequence
    from estimator.synth import SynthSpec, synthesize

    write_sequence(path, synthesize(SynthSpec(n_cameras=2, n_frames=n_frames, seed=seed, azimuths=(60.0, 150.0),
                                              elevations=(10.0, 10.0), image_size=image_size)))
    return path


def sequence_zip(seq_dir: Path) -> bytes:
    """Zip a sequence folder (under one top folder, as a user would)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(seq_dir.rglob("*")):
            if p.is_file():
                zf.write(p, Path(seq_dir.name) / p.relative_to(seq_dir))
    return buf.getvalue()
