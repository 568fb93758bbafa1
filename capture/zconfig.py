"""The one place that turns ``--mode/--connect/--listen/--config`` into a ``zenoh.Config``.

Defaults keep everything on this host: peer mode, multicast scouting off,
listening on an ephemeral loopback port and connecting to
``tcp/127.0.0.1:7447`` (the service or a router) unless told otherwise.
Connect retries start at 250 ms so a restarted peer or router is found again
quickly. Options given on the command line override the config file.
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Sequence

import zenoh

__all__ = [
    "DEFAULT_ENDPOINT",
    "LOOPBACK_ANY",
    "add_zenoh_arguments",
    "build_config",
    "config_from_args",
]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
LOOPBACK_ANY = "tcp/127.0.0.1:0"
MODES = ("peer", "client", "router")
_RETRY = {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2}


def build_config(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: str | os.PathLike[str] | None = None,
                 multicast: bool = False) -> zenoh.Config:
    """Build a session config.

    Parameters
    ----------
    mode : "peer", "client" or "router".
    connect, listen : endpoints such as ``tcp/127.0.0.1:7447``. When both are
        empty and no config file is given, a peer or client connects to
        :data:`DEFAULT_ENDPOINT`; a peer or router listens on loopback only.
    config_file : a zenoh JSON5 config; the other arguments override it.
    multicast : enable multicast scouting (off: tests and defaults stay on-host).
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
    if config_file is not None:
        try:
            conf = zenoh.Config.from_file(os.fspath(config_file))
        except Exception as exc:  # zenoh raises ZError with the parser's message
            raise ValueError(f"cannot read zenoh config {config_file}: {exc}") from None
    else:
        conf = zenoh.Config()
    connect, listen = list(connect), list(listen)
    if config_file is None:
        if not connect and not listen and mode != "router":
            connect = [DEFAULT_ENDPOINT]
        if not listen and mode != "client":
            listen = [DEFAULT_ENDPOINT if mode == "router" else LOOPBACK_ANY]
    conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(connect))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(listen))
    conf.insert_json5("connect/retry", json.dumps(_RETRY))
    conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    return conf


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--mode/--connect/--listen/--config`` to a parser (repeatable endpoints)."""
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", choices=MODES, default="peer", help="session mode (default: peer)")
    group.add_argument("--connect", "-e", action="append", default=None, metavar="ENDPOINT",
                       help=f"endpoint to connect to (default: {DEFAULT_ENDPOINT})")
    group.add_argument("--listen", "-l", action="append", default=None, metavar="ENDPOINT",
                       help=f"endpoint to listen on (default: {LOOPBACK_ANY})")
    group.add_argument("--config", dest="zenoh_config", default=None, metavar="FILE",
                       help="zenoh JSON5 config file; the options above override it")
    group.add_argument("--multicast", action="store_true",
                       help="enable multicast scouting (off by default: on-host only)")


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The ``zenoh.Config`` for arguments added by :func:`add_zenoh_arguments`."""
    return build_config(mode=args.mode, connect=args.connect or (), listen=args.listen or (),
                        config_file=args.zenoh_config, multicast=args.multicast)
