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

Access rules (``POSECAL_ZENOH_AGENTS``, :func:`access_rules`): on the node that
the agents connect to (the service, or a router), Zenoh's ``access_control``
with ``default_permission: deny``, generated from the rig's cameras: an agent may
put only its own camera's silhouettes and subscribe only to its own camera's
priors; names in ``POSECAL_ZENOH_TRUSTED`` (the service behind a router) may do
everything; anyone else nothing. Zenoh enforces them on that node, for messages
crossing its links (zenoh.io/docs/manual/access-control).
"""

from __future__ import annotations

import argparse
import json
import os
import re
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
    "access_rules",
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
LEASE = "transport/link/tx/lease"  # milliseconds
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")  # rig, camera and agent names (capture.wire's)
# Every message kind Zenoh 1.x's access control knows (what a trusted name may send and receive).
ACL_MESSAGES = ("put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
                "liveliness_token", "declare_liveliness_subscriber", "liveliness_query")


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
    agents: dict[str, str] = Field(default_factory=dict, description="access rules on the node agents "
                                   "connect to: agent name -> 'rig/camera' (JSON). The name is the "
                                   "agent's certificate CN under mtls and its user name with a "
                                   "dictionary file (both when both are set); it may publish only "
                                   "that camera's silhouettes and read only its priors")
    trusted: list[str] = Field(default_factory=list, description="names (CN / user, as for agents) that "
                               "may do everything: the service, when the rules are on a router")

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
        if self.agents or self.trusted:
            if not self.mtls and self.dictionary_file is None:
                raise ValueError("zenoh access rules name agents by their certificate (mtls) or their "
                                 "user name (dictionary_file): set one of them")
            for name in (*self.agents, *self.trusted):
                if not _NAME.match(name):
                    raise ValueError(f"zenoh agent and trusted names must match {_NAME.pattern}, got {name!r}")
            for name, place in self.agents.items():
                rig, _, camera = place.partition("/")
                if not (_NAME.match(rig) and _NAME.match(camera)):
                    raise ValueError(f"zenoh agent {name!r}: give its camera as 'rig/camera', got {place!r}")
            if both := set(self.agents) & set(self.trusted):
                raise ValueError(f"zenoh names both an agent and trusted: {sorted(both)}")
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
        if self.agents or self.trusted:
            out["access_control"] = access_rules(self.agents, self.trusted, by_certificate=self.mtls,
                                                 by_user=self.dictionary_file is not None)
        return out


def access_rules(agents: dict[str, str], trusted: Sequence[str] = (), *, by_certificate: bool = True,
                 by_user: bool = False) -> dict[str, object]:
    """Zenoh 1.x ``access_control`` for a rig: deny by default; each agent may put its
    camera's silhouettes and subscribe to its priors (and be sent those); trusted names
    may do everything.

    Parameters
    ----------
    agents : name -> ``"rig/camera"``; the name is a certificate CN (``by_certificate``)
        and/or a user name (``by_user``; both must match when both are set).
    trusted : names allowed every message both ways (the service behind a router).

    The node enforcing them (the service, or a router) checks its links' messages:
    ``ingress`` what arrives from the agent, ``egress`` what it sends to it. The
    service's own subscription to every camera (``posecal/*/*/silhouette``) is sent to
    the agents so that they publish at all; it tells them nothing else.
    """
    from .wire import feedback_key, silhouette_key

    def subject(name: str) -> dict[str, object]:
        out: dict[str, object] = {"id": name}
        if by_certificate:
            out["cert_common_names"] = [name]
        if by_user:
            out["usernames"] = [name]
        if len(out) == 1:
            raise ValueError("access rules need certificates (mtls) or user names to tell agents apart")
        return out

    def rule(rule_id: str, flow: str, messages: Sequence[str], keys: Sequence[str]) -> dict[str, object]:
        return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": list(messages),
                "key_exprs": list(keys)}

    rules = [rule("hear-the-service", "egress", ["declare_subscriber"], [silhouette_key("*", "*")])]
    subjects, policies = [], []
    for name, place in sorted(agents.items()):
        rig, _, camera = place.partition("/")
        own, priors = silhouette_key(rig, camera), feedback_key(rig, camera)
        rules += [rule(f"{name}-publish", "ingress", ["put"], [own]),
                  rule(f"{name}-subscribe", "ingress", ["declare_subscriber"], [priors]),
                  rule(f"{name}-receive", "egress", ["put"], [priors])]
        subjects.append(subject(name))
        policies.append({"id": f"agent-{name}", "subjects": [name],
                         "rules": [f"{name}-publish", f"{name}-subscribe", f"{name}-receive",
                                   "hear-the-service"]})
    if trusted:
        rules += [rule("everything-in", "ingress", ACL_MESSAGES, ["**"]),
                  rule("everything-out", "egress", ACL_MESSAGES, ["**"])]
        for name in sorted(trusted):
            subjects.append(subject(name))
        policies.append({"id": "trusted", "subjects": sorted(trusted),
                         "rules": ["everything-in", "everything-out"]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def _existing(path: Path | None, what: str) -> Path:
    if path is None or not Path(path).is_file():
        raise ValueError(f"zenoh {what} {path} does not exist")
    return Path(path).expanduser().resolve()


def build_config(*, mode: str = "peer", connect: Sequence[str] = (), listen: Sequence[str] = (),
                 config_file: str | os.PathLike[str] | None = None,
                 multicast: bool = False, access: ZenohAccess | None = None,
                 lease_s: float | None = None) -> zenoh.Config:
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
    lease_s : the transport lease this session announces (``transport/link/tx/lease``;
        Zenoh's default 10 s; keep-alives go every lease / ``keep_alive`` (4)): the other
        side closes a link silent this long, so it bounds how soon a node that vanished
        without closing its links (host lost, SIGSTOP) is seen gone. None = the config's.
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
    if lease_s is not None:
        conf.insert_json5(LEASE, json.dumps(int(lease_s * 1000)))
    for key, value in (access.entries() if access is not None else {}).items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``--mode/--connect/--listen/--config`` to a parser (repeatable endpoints)."""
    group = parser.add_argument_group(
        "zenoh", "user/password authentication and TLS come from POSECAL_ZENOH_USER, "
        "POSECAL_ZENOH_PASSWORD_FILE, POSECAL_ZENOH_DICTIONARY_FILE, POSECAL_ZENOH_TLS_ROOT_CA, "
        "POSECAL_ZENOH_TLS_CERTIFICATE, POSECAL_ZENOH_TLS_PRIVATE_KEY and POSECAL_ZENOH_MTLS; access "
        "rules on a listener from POSECAL_ZENOH_AGENTS and POSECAL_ZENOH_TRUSTED "
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
