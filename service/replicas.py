"""Replicas of the service on one Zenoh network: who is alive, and which one estimates a rig.

Each replica declares a Zenoh liveliness token ``posecal/@replicas/<replica_id>/<zid>``
and subscribes to ``posecal/@replicas/*/*`` (with history), so every replica knows the
same set of alive replicas: Zenoh removes a token when its session closes, or when
the links to it expire (the transport lease, ``replica_lease_s``). The owner of a rig
is chosen by rendezvous (highest-random-weight) hashing of the rig's name over the
alive replica ids: every replica computes the same owner from the same membership,
so nothing is negotiated, and when a replica leaves or joins only the rigs it owned
or now owns move.

The Zenoh session id in the key makes every token's key unique: two sessions under
one ``replica_id`` are told apart (the one with the smaller session id estimates, the
other estimates nothing and logs why), and a token that was deleted never comes back
under the same key. A replica that starts while another session holds its id refuses
to start (:class:`ReplicaConflict`), after waiting long enough for the token of a
crashed predecessor to expire.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field

import zenoh

__all__ = ["REPLICAS_KEY", "ReplicaConflict", "Replicas", "rendezvous_owner"]

log = logging.getLogger(__name__)

REPLICAS_KEY = "posecal/@replicas"  # a verbatim chunk: `posecal/**` subscribers do not match it
_SETTLE_S = 0.5  # after subscribing: Zenoh delivers the existing tokens within milliseconds
_MAX_CACHED = 4096  # rig owners cached per membership (rig names come from peers: bounded)


def _weight(replica: str, rig: str) -> int:
    return int.from_bytes(hashlib.blake2b(f"{replica}\0{rig}".encode(), digest_size=8).digest(), "big")


def rendezvous_owner(rig: str, replicas: Iterable[str]) -> str | None:
    """The replica that estimates ``rig``: the highest hash of (replica, rig); None if there is none.

    Deterministic across processes and hosts (blake2b, not Python's salted ``hash``)."""
    return max(replicas, key=lambda r: (_weight(r, rig), r), default=None)


class ReplicaConflict(RuntimeError):
    """Another live session already uses this replica id."""


@dataclass(frozen=True)
class _View:
    """One membership, and the owners computed from it (filled lazily, replaced on change)."""

    sessions: dict[str, frozenset[str]]  # replica id -> Zenoh session ids holding a token
    active: bool  # False: another session with our id and a smaller session id estimates instead
    owners: dict[str, str] = field(default_factory=dict)


class Replicas:
    """This replica's liveliness token and the alive replicas as Zenoh reports them; thread-safe.

    ``on_change(fn)`` registers ``fn()``, called on Zenoh's thread after each change of
    membership (keep it short). Use as a context manager, or call :meth:`close`.
    """

    def __init__(self, session: zenoh.Session, replica_id: str, *, lease_s: float) -> None:
        self.replica_id = replica_id
        self.zid = str(session.zid())
        self._lock = threading.Lock()
        self._tokens: set[tuple[str, str]] = set()  # (replica id, session id) alive
        self._gone: set[tuple[str, str]] = set()  # deleted: a late query reply must not revive it
        self._listeners: list[Callable[[], None]] = []
        self._view = _View({}, True)
        liveliness = session.liveliness()
        self._sub = liveliness.declare_subscriber(f"{REPLICAS_KEY}/*/*", self._on_sample, history=True)
        try:
            time.sleep(_SETTLE_S)
            for reply in liveliness.get(f"{REPLICAS_KEY}/*/*", timeout=1.0):
                if reply.ok is not None:
                    self._update(str(reply.ok.key_expr), alive=True, from_query=True)
            self._wait_for_own_id(2 * lease_s + _SETTLE_S)
            self._token = liveliness.declare_token(f"{REPLICAS_KEY}/{replica_id}/{self.zid}")
        except BaseException:
            self._sub.undeclare()
            raise
        self._update(f"{REPLICAS_KEY}/{replica_id}/{self.zid}", alive=True)  # before Zenoh echoes it

    def _wait_for_own_id(self, timeout_s: float) -> None:
        """Wait up to ``timeout_s`` for other sessions under our id to go (a crashed predecessor's
        token lasts until its lease expires); raise :class:`ReplicaConflict` if one stays."""
        deadline = time.monotonic() + timeout_s
        while others := self.sessions().get(self.replica_id):
            if time.monotonic() > deadline:
                raise ReplicaConflict(
                    f"replica id {self.replica_id!r} is already alive on this Zenoh network (session "
                    f"{', '.join(sorted(others))}): two replicas with one id would estimate the same rigs; "
                    "give each replica its own --replica-id (POSECAL_REPLICA_ID)")
            time.sleep(0.1)

    # -- membership (Zenoh's thread) ---------------------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._update(str(sample.key_expr), alive=sample.kind == zenoh.SampleKind.PUT)

    def _update(self, key: str, *, alive: bool, from_query: bool = False) -> None:
        name, _, zid = key.removeprefix(f"{REPLICAS_KEY}/").partition("/")
        if not name or not zid or "/" in zid:
            return
        token = (name, zid)
        with self._lock:
            if alive:
                if token in self._tokens or (from_query and token in self._gone):
                    return
                self._tokens.add(token)
            else:
                self._gone.add(token)  # session ids are never reused: a token deleted stays deleted
                if token not in self._tokens:
                    return
                self._tokens.discard(token)
            sessions: dict[str, set[str]] = {}
            for r, z in self._tokens:
                sessions.setdefault(r, set()).add(z)
            mine = sessions.get(self.replica_id, {self.zid})
            active = min(mine) == self.zid or self.zid not in mine
            if not active and self._view.active:
                log.error("replica id %s is also used by zenoh session %s: that one estimates, this one "
                          "(%s) estimates nothing until it goes", self.replica_id, min(mine), self.zid)
            self._view = _View({r: frozenset(z) for r, z in sessions.items()}, active)
            listeners = list(self._listeners)
        log.info("replica %s (zenoh %s) %s: alive %s", name, zid, "joined" if alive else "left",
                 ", ".join(self.alive()))
        for fn in listeners:
            try:
                fn()
            except Exception:  # a listener's bug must not stop membership updates
                log.exception("replica membership listener failed")

    # -- queries (any thread) ----------------------------------------------------------------
    def alive(self) -> list[str]:
        """The alive replica ids (this one included once it has joined), sorted."""
        return sorted(self._view.sessions)

    def sessions(self) -> dict[str, list[str]]:
        """Replica id -> Zenoh session ids of the *other* sessions holding a token."""
        return {r: sorted(z - {self.zid}) for r, z in self._view.sessions.items() if z - {self.zid}}

    def owner(self, rig: str) -> str | None:
        """The replica that estimates ``rig`` now (None before this replica has joined)."""
        view = self._view
        owner = view.owners.get(rig)
        if owner is None:
            if len(view.owners) >= _MAX_CACHED:
                view.owners.clear()
            owner = view.owners[rig] = rendezvous_owner(rig, view.sessions)
        return owner

    def owns(self, rig: str) -> bool:
        """Whether this replica estimates ``rig`` (cheap: cached per membership)."""
        return self._view.active and self.owner(rig) == self.replica_id

    @property
    def active(self) -> bool:
        """False while another session with this replica id (and a smaller session id) is alive."""
        return self._view.active

    def on_change(self, fn: Callable[[], None]) -> None:
        """Call ``fn()`` after every change of membership."""
        with self._lock:
            self._listeners.append(fn)

    def close(self) -> None:
        """Leave: undeclare the token (the others take this replica's rigs) and the subscriber."""
        for entity in (self._token, self._sub):
            try:
                entity.undeclare()
            except Exception:  # the session may already be closed
                pass

    def __enter__(self) -> Replicas:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
