"""A Zenoh router in a Python session, for rigs that want one (no ``zenohd`` needed).

Agents and the service connect to it (``--connect tcp/HOST:7447``); it routes
between them and keeps running when any of them restarts.
"""

from __future__ import annotations

import logging
import threading

import zenoh

from .agent import _StopOnSignals

__all__ = ["main"]

log = logging.getLogger(__name__)


def main(conf: zenoh.Config, *, stop: threading.Event | None = None) -> None:
    """Serve as a router until SIGINT/SIGTERM or ``stop``; ``conf`` should have mode "router"."""
    stop = stop or threading.Event()
    with _StopOnSignals(stop), zenoh.open(conf) as session:
        log.info("zenoh router %s listening on %s", session.zid(),
                 conf.get_json("listen/endpoints"))
        while not stop.wait(1.0):
            pass
    log.info("router stopped")
