"""The one place that turns ``--mode/--connect/--listen/--config`` into a ``zenoh.Config``.

Defaults keep everything on this host: peer mode, multicast scouting off,
listening on an ephemeral loopback port and connecting to
``tcp/127.0.0.1:7447`` (the service or a router) unless told otherwise.
Connect retries start at 250 ms so a restarted peer or router is found again
quickly. Options given on the command line override the config file.

Access (:class:`ZenohAccess`, ``POSECAL_ZENOH_*`` variables, the same for the
service, the agents and the router): user/password authentication
(``transport/auth/usrpwd``: the listening side checks a dictionary file of
``user:password`` lines, the connecting side presents its own) and TLS
(``tls/HOST:PORT`` endpoints; ``transport/link/tls``: the lab CA, this host's
certificate and key, mutual TLS). Key names are Zenoh 1.x's
(``DEFAULT_CONFIG.json5``; zenoh.io/docs/manual/tls, .../user-password).
"""

from __future__ import annotations

import argparse
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, SecretStr, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

if TYPE_CHECKING:
    import zenoh

__all__ = [
    "DEFAULT_ENDPOINT",
    "LOOPBACK_ANY",
    "ZenohAccess",
    "add_zenoh_arguments",
    "build_config",
    "config_from_args",
]

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
LOOPBACK_ANY = "tcp/127.0.0.1:0"
MODES = ("peer", "client", "router")
_RETRY = {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2}
USRPWD = "transport/auth/usrpwd"
TLS = "transport/link/tls"


class ZenohAccess(BaseSettings):
    """Who may join the Zenoh network, and how links are protected (env: ``POSECAL_ZENOH_*``).

    Nothing set = no authentication, plain TCP (fine on loopback only).
    """

    model_config = SettingsConfigDict(env_prefix="POSECAL_ZENOH_", frozen=True, extra="ignore")

    user: str | None = Field(None, description="user name this session presents (usrpwd)")
    password: SecretStr | None = Field(None, description="its password (prefer password_file)")
    password_file: Path | None = Field(None, description="a file holding the password (first line)")
    dictionary_file: Path | None = Field(None, description="``user:password`` lines: the peers this "
                                         "session accepts on its listen endpoints (the service, a router)")
    tls_root_ca: Path | None = Field(None, description="CA certificate (PEM) that the other side's "
                                     "certificate must be signed by")
    tls_certificate: Path | None = Field(None, description="this host's certificate (PEM): served on "
                                         "tls/ listen endpoints, and presented when connecting with mTLS")
    tls_private_key: Path | None = Field(None, description="its private key (PEM)")
    mtls: bool = Field(False, description="mutual TLS: both sides present a certificate signed by the CA")

    @model_validator(mode="after")
    def _check(self) -> "ZenohAccess":
        if self.password is not None and self.password_file is not None:
            raise ValueError("give the zenoh password or a password file, not both")
        if (self.user is None) != (self.password is None and self.password_file is None):
            raise ValueError("zenoh user/password authentication needs both a user and a password")
        if (self.tls_certificate is None) != (self.tls_private_key is None):
            raise ValueError("a TLS certificate needs its private key, and a key its certificate")
        if self.mtls and (self.tls_certificate is None or self.tls_root_ca is None):
            raise ValueError("mutual TLS needs tls_root_ca, tls_certificate and tls_private_key")
        return self

    def secret(self) -> str | None:
        """The password (read from ``password_file`` if given)."""
        if self.password_file is not None:
            lines = _existing(self.password_file, "password file").read_text().splitlines()
            if not lines or not lines[0].strip():
                raise ValueError(f"zenoh password file {self.password_file} is empty")
            return lines[0].strip()
        return None if self.password is None else self.password.get_secret_value()

    def entries(self) -> dict[str, object]:
        """The config keys this sets (``path -> value``), files checked to exist."""
        out: dict[str, object] = {}
        if self.user is not None:
            out[f"{USRPWD}/user"] = self.user
            out[f"{USRPWD}/password"] = self.secret()
        if self.dictionary_file is not None:
            out[f"{USRPWD}/dictionary_file"] = str(_existing(self.dictionary_file, "user/password dictionary"))
        if self.tls_root_ca is not None:
            out[f"{TLS}/root_ca_certificate"] = str(_existing(self.tls_root_ca, "TLS CA certificate"))
        if self.tls_certificate is not None:
            cert = str(_existing(self.tls_certificate, "TLS certificate"))
            key = str(_existing(self.tls_private_key, "TLS private key"))
            out.update({f"{TLS}/listen_certificate": cert, f"{TLS}/listen_private_key": key,
                        f"{TLS}/connect_certificate": cert, f"{TLS}/connect_private_key": key})
        if self.mtls:
            out[f"{TLS}/enable_mtls"] = True
        return out


def _existing(path: Path | None, what: str) -> Path:
    if path is None or not Path(path).is_file():
        raise ValueError(f"zenoh {what} {path} does not exist")
    return Path(path).expanduser().resolve()


def build_config(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: str | os.PathLike[str] | None = None,
                 multicast: bool = False, access: ZenohAccess | None = None) -> zenoh.Config:
    """Build a session config.

    Parameters
    ----------
    mode : "peer", "client" or "router".
    connect, listen : endpoints such as ``tcp/127.0.0.1:7447``. When both are
        empty and no config file is given, a peer or client connects to
        :data:`DEFAULT_ENDPOINT`; a peer or router listens on loopback only.
    config_file : a zenoh JSON5 config; the other arguments override it.
    multicast : enable multicast scouting (off: tests and defaults stay on-host).
    access : authentication and TLS (:class:`ZenohAccess`); None = none.
    """
    import zenoh

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
    for key, value in (access.entries() if access is not None else {}).items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--mode/--connect/--listen/--config`` to a parser (repeatable endpoints)."""
    group = parser.add_argument_group(
        "zenoh", "user/password authentication and TLS come from POSECAL_ZENOH_USER, "
        "POSECAL_ZENOH_PASSWORD_FILE, POSECAL_ZENOH_DICTIONARY_FILE, POSECAL_ZENOH_TLS_ROOT_CA, "
        "POSECAL_ZENOH_TLS_CERTIFICATE, POSECAL_ZENOH_TLS_PRIVATE_KEY and POSECAL_ZENOH_MTLS "
        "(docs/SERVICE.md, Access)")
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
    """The ``zenoh.Config`` for arguments added by :func:`add_zenoh_arguments`, with the
    access settings of the environment (``POSECAL_ZENOH_*``, :class:`ZenohAccess`)."""
    from pydantic import ValidationError

    try:
        access = ZenohAccess()
    except ValidationError as exc:
        raise ValueError(f"zenoh access settings: {exc.errors()[0]['msg']}") from None
    return build_config(mode=args.mode, connect=args.connect or (), listen=args.listen or (),
                        config_file=args.zenoh_config, multicast=args.multicast, access=access)
