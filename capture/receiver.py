"""Validating Zenoh subscribers: malformed messages are logged, counted and skipped.

:class:`ValidatingSubscriber` decodes every sample with :func:`capture.wire.decode`
and hands good messages to a callback or a bounded queue; a bad payload
never reaches the consumer and never stops the subscriber.
:class:`SilhouetteReceiver` adds what a consumer of silhouettes needs: the
receive time, and per camera the agent epoch and sequence, so it can tell an
agent restart (new epoch) and lost messages (sequence gaps).

Nothing a peer sends can raise out of the receive callback: every failure is
a counted rejection with a one-line, rate-limited log, by reason (``codes``:
a fixed set of words, :data:`REJECT_CODES`). A silhouette stamped further
ahead of the receiver's clock than ``max_clock_ahead_s`` (``epoch_ns`` or
``capture_ns``) is rejected rather than adopted, and an epoch is only
"current" while it is heard from: one forged message cannot shut a camera out.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Generic, Self, TypeVar

import zenoh

from .wire import FeedbackMessage, SilhouetteMessage, WireError, decode, parse_key, silhouette_key

__all__ = ["REJECT_CODES", "Received", "ReceiverStats", "SilhouetteReceiver", "ValidatingSubscriber"]

log = logging.getLogger(__name__)

M = TypeVar("M", SilhouetteMessage, FeedbackMessage)
_LOG_FIRST = 20  # rejections logged one by one, then one in _LOG_EVERY
_LOG_EVERY = 100
_MAX_REASONS = 64  # distinct reason texts kept in ReceiverStats.reasons (then "other")
# Why a message was rejected, as a metric label: the wire's WireError codes, then the receiver's.
REJECT_CODES = ("envelope", "header", "field", "image", "key", "epoch_future", "capture_future", "internal")


@dataclass
class ReceiverStats:
    """Counters of one subscriber; read a snapshot with ``receiver.stats()``."""

    accepted: int = 0
    rejected: int = 0
    reasons: Counter[str] = field(default_factory=Counter)
    overflow: int = 0  # accepted but dropped because the queue was full
    restarts: int = 0  # epochs that replaced an earlier one of the same camera
    lost: int = 0  # sequence numbers skipped within an epoch
    stale: int = 0  # messages from an epoch older than the current one (dropped)
    codes: Counter[str] = field(default_factory=Counter)  # rejected by REJECT_CODES
    readopted: int = 0  # older epochs taken back after the newer one fell silent


class ValidatingSubscriber(Generic[M]):
    """Subscribe to ``key_expr`` and accept only valid messages of type ``expect``.

    With ``on_message`` each accepted message is passed to it on Zenoh's
    network thread (``indirect=False``: one thread hop less; in one loaded
    run of the loopback benchmark p99 publish-to-receive went from 10.3 to
    6.7 ms), so keep it short;
    otherwise messages are queued for :meth:`get`. Use as a context manager,
    or call :meth:`close`.

    ``max_image_size`` (width, height), when given, rejects messages for larger
    frames: an agent passes its own frame size, so that a prior claiming a huge
    image is refused before its canvas is allocated.
    """

    def __init__(self, session: zenoh.Session, key_expr: str, expect: type[M], *,
                 on_message: Callable[[M], None] | None = None, maxsize: int = 10_000,
                 max_image_size: tuple[int, int] | None = None) -> None:
        self.key_expr = key_expr
        self.expect = expect
        self.max_image_size = max_image_size
        self._on_message = on_message
        self._queue: queue.Queue = queue.Queue(maxsize)
        self._lock = threading.Lock()
        self._stats = ReceiverStats()
        self._sub = session.declare_subscriber(
            key_expr, zenoh.handlers.Callback(self._on_sample, indirect=False))

    def _on_sample(self, sample: zenoh.Sample) -> None:
        receive_ns = time.time_ns()  # on arrival, before decoding
        key = str(sample.key_expr)
        try:
            msg = decode(sample.payload.to_bytes(), expect=self.expect)
            rig, camera, _ = parse_key(key)
            if (rig, camera) != (msg.rig, msg.camera):
                raise WireError(f"message for {msg.rig}/{msg.camera} arrived on {key}", "key")
            limit = self.max_image_size
            if limit is not None and (msg.image_size[0] > limit[0] or msg.image_size[1] > limit[1]):
                raise WireError(f"image_size {msg.image_size} exceeds this receiver's {limit}", "image")
        except WireError as exc:
            self._reject(key, str(exc), exc.code)
            return
        except Exception as exc:  # nothing a peer sends may escape: counted, one line, no traceback
            self._reject(key, f"undecodable ({type(exc).__name__}: {exc})", "internal")
            return
        item = self._accept(msg, receive_ns)
        if item is None:
            return
        try:
            if self._on_message is not None:
                self._on_message(item)
            else:
                self._queue.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._stats.overflow += 1
        except Exception:  # a consumer bug must not kill the subscriber
            log.exception("message handler failed on %s", key)

    def _accept(self, msg: M, receive_ns: int):
        """Count ``msg`` and return what to deliver (None = drop); subclasses add state."""
        with self._lock:
            self._stats.accepted += 1
        return msg

    def _reject(self, key: str, reason: str, code: str) -> None:
        with self._lock:
            s = self._stats
            s.rejected += 1
            s.codes[code] += 1
            text = reason.split(":")[0]
            s.reasons[text if text in s.reasons or len(s.reasons) < _MAX_REASONS else "other"] += 1
            n = s.rejected
        if n <= _LOG_FIRST or n % _LOG_EVERY == 0:
            log.warning("rejected message #%d on %.200s (%s): %.300s", n, key, code, reason)

    def get(self, timeout: float | None = None):
        """The next accepted message (queue mode), or None after ``timeout`` seconds."""
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def stats(self) -> ReceiverStats:
        """A copy of the counters."""
        with self._lock:
            s = self._stats
            return dataclasses.replace(s, reasons=Counter(s.reasons), codes=Counter(s.codes))

    def close(self) -> None:
        self._sub.undeclare()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, slots=True)
class Received:
    """A silhouette as delivered: ``new_epoch`` is True on the first message of
    an agent run (a restart if the camera was seen before); ``lost`` counts
    sequence numbers skipped since the previous message of the same epoch."""

    message: SilhouetteMessage
    receive_ns: int
    new_epoch: bool
    lost: int

    @property
    def latency_ns(self) -> int:
        """Capture-to-receive time (same clock, or clocks synchronised by NTP/PTP)."""
        return self.receive_ns - self.message.capture_ns


class SilhouetteReceiver(ValidatingSubscriber[SilhouetteMessage]):
    """Silhouettes of ``rig``/``camera`` (``"*"`` = all), delivered as :class:`Received`.

    ``max_clock_ahead_s``: a message whose ``epoch_ns`` or ``capture_ns`` is
    further ahead of this receiver's clock is rejected (``epoch_future``,
    ``capture_future``; None = no check). A message of an older epoch than the
    camera's current one is stale (dropped) while the current epoch is heard
    from; once that has been silent for ``epoch_silence_s`` the older epoch is
    taken back (``readopted``). Epochs are kept for the ``max_streams`` cameras
    heard from most recently.
    """

    def __init__(self, session: zenoh.Session, rig: str = "*", camera: str = "*", *,
                 on_message: Callable[[Received], None] | None = None,
                 maxsize: int = 10_000, max_clock_ahead_s: float | None = 30.0,
                 epoch_silence_s: float = 3.0, max_streams: int = 4096) -> None:
        # (rig, camera) -> (epoch_ns, last seq, last receive_ns of that epoch), least recent first
        self._epochs: OrderedDict[tuple[str, str], tuple[int, int, int]] = OrderedDict()
        self._ahead_ns = None if max_clock_ahead_s is None else int(max_clock_ahead_s * 1e9)
        self._silence_ns = int(epoch_silence_s * 1e9)
        self._max_streams = max_streams
        super().__init__(session, silhouette_key(rig, camera), SilhouetteMessage,
                         on_message=on_message, maxsize=maxsize)  # type: ignore[arg-type]

    def _accept(self, msg: SilhouetteMessage, receive_ns: int) -> Received | None:
        if self._ahead_ns is not None:
            for name in ("epoch_ns", "capture_ns"):
                ahead = getattr(msg, name) - receive_ns
                if ahead > self._ahead_ns:
                    self._reject(silhouette_key(msg.rig, msg.camera),
                                 f"{name} is {ahead / 1e9:.3g} s ahead of this receiver's clock",
                                 name.replace("_ns", "_future"))
                    return None
        cam = (msg.rig, msg.camera)
        with self._lock:
            known = self._epochs.get(cam)
            readopt = (known is not None and msg.epoch_ns < known[0]
                       and receive_ns - known[2] > self._silence_ns)
            if known is not None and msg.epoch_ns < known[0] and not readopt:
                self._stats.stale += 1
                return None
            new_epoch = known is None or msg.epoch_ns != known[0]
            lost = 0
            if readopt:  # the newer epoch fell silent (a forged one, or a clock stepped back)
                self._stats.readopted += 1
            elif new_epoch:
                if known is not None:  # a restart: seq 0.. of the new run should have come
                    self._stats.restarts += 1
                    lost = msg.seq
            elif msg.seq > known[1]:
                lost = msg.seq - known[1] - 1
            self._stats.lost += lost
            if new_epoch or msg.seq > known[1]:
                self._epochs[cam] = (msg.epoch_ns, msg.seq, receive_ns)
            else:
                self._epochs[cam] = (known[0], known[1], receive_ns)
            self._epochs.move_to_end(cam)
            if len(self._epochs) > self._max_streams:
                self._epochs.popitem(last=False)
            self._stats.accepted += 1
        return Received(msg, receive_ns, new_epoch, lost)
