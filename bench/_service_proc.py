"""Start ``posecal serve`` as a subprocess on loopback for the service benchmarks."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import httpx

from service.server import free_port


class ServiceProcess:
    """``python -m service.cli serve ...`` on 127.0.0.1 with its files under ``workdir``."""

    def __init__(self, workdir: Path, *extra: str, model: str | None = None, timeout: float = 600.0) -> None:
        workdir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.zenoh = f"tcp/127.0.0.1:{free_port()}"
        cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(self.port),
               "--listen", self.zenoh, "--db", str(workdir / "jobs.db"),
               "--data-dir", str(workdir / "data"), *extra]
        if model:
            cmd += ["--model", model]
        self.log_path = workdir / "service.log"
        self.proc = subprocess.Popen(cmd, stdout=open(self.log_path, "w"), stderr=subprocess.STDOUT)
        self.url = f"http://127.0.0.1:{self.port}"
        self.client = httpx.Client(base_url=self.url, timeout=30.0)
        deadline = time.monotonic() + timeout
        while True:
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited; see {self.log_path}")
            try:
                if self.client.get("/healthz").status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                self.close()
                raise RuntimeError("the service did not start")
            time.sleep(0.2)

    def close(self) -> None:
        self.client.close()
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()

    def __enter__(self) -> "ServiceProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
