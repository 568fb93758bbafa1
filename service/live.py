"""Live estimation: silhouettes from Zenoh -> synchronized frames -> sliding windows -> estimates.

Per rig:

1. :class:`FrameAssembler` groups the cameras' messages into frame sets: by
   ``frame_index`` when the agents say ``sync="index"`` (hardware-triggered or
   synthetic rigs), else by ``capture_ns`` within ``sync_tolerance_ms``. A frame
   set is closed when every expected camera is in it or has already sent a later
   frame (Zenoh keeps each publisher's order), or after ``max_wait_ms``; missing
   cameras then count as "no data". Late messages (for a closed frame) and
   duplicates are dropped and counted. A camera silent for ``camera_timeout_s``
   is no longer waited for (and shows as ``stale`` in the rig's summary). An
   index-synchronised agent that restarts (new epoch) numbers its frames from 0
   again: its indices are re-based onto the rig's (an offset per camera run,
   from the other cameras' newest frame and frame period at the message's
   capture time), so its frames join the current frame sets; with no other
   camera live, or ``sync="time"``, the rig's assembly starts over instead.
2. :class:`WindowBuffer` cuts windows of ``window_length`` frame sets every
   ``window_hop``; a jump in frame index larger than half a window starts over.
3. Windows wait in a bounded queue (oldest dropped on overflow); consumer
   threads estimate each (:func:`service.worker.estimate_window`: the window's cameras
   split over the live worker processes, each camera always in the same one),
   smooth the viewpoints (:class:`estimator.windows.ViewpointTrack`), publish the result on
   ``posecal/<rig>/estimate``, keep it for the REST API and log it to Rerun.
4. Feedback (§7.1, ``feedback``): the window's estimate predicts the next
   ``feedback_ahead`` frames of every camera; their rendered, registered priors
   go to ``posecal/<rig>/<camera>/feedback`` ahead of the frames they are for.

With several replicas (:mod:`service.replicas`, docs/SERVICE.md, "Several replicas")
each estimates only the rigs that rendezvous hashing gives it: a silhouette of another
replica's rig is skipped by its key, before it is decoded; when the membership
changes, rigs now owned elsewhere are dropped (as forgotten ones) and rigs now
owned here start from their next frames.

Before a message touches a rig it must be believable (docs/SERVICE.md, "Limits
and refusals"): the receiver rejects clocks from the future; a new rig beyond
``max_rigs`` or a new camera beyond ``max_cameras`` is refused unless a silent
one can make room; a ``frame_index`` further than ``max_index_ahead`` ahead of
the rig's is dropped until a few in a row agree. Rigs and cameras silent for
``rig_expiry_s`` are forgotten, with their metrics.

The Zenoh callback thread only does bookkeeping; nothing blocks the event loop.
"""

from __future__ import annotations

import collections
import concurrent.futures
import dataclasses
import json
import logging
import queue
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh
from prometheus_client import Counter

from capture.receiver import Received, SilhouetteReceiver
from capture.wire import Box, FeedbackMessage, Quality, SilhouetteMessage, encode, estimate_key, feedback_key
from capture.refine import track_from_segmentations
from estimator.joints import N_JOINTS
from estimator.pipeline import CameraTrack
from estimator.windows import ViewpointTrack, earlier_azimuths, own_azimuth

from .metrics import Metrics
from .replicas import Replicas
from .settings import Settings
from .worker import (PinnedPools, StageBundle, WindowBefore, estimate_window, predict_feedback, register_stage,
                     warm_window)

__all__ = ["FrameAssembler", "FrameSet", "LiveService", "WindowBuffer"]

log = logging.getLogger(__name__)

_REBASE_AFTER = 5  # frames in a row, each ahead of the rig but agreeing, that move it there
_EXPIRE_EVERY_S = 1.0
_MAX_HEARD_RIGS = 4096  # rig names remembered from other replicas' silhouettes (peers choose them)


class _OwnedReceiver(SilhouetteReceiver):
    """A :class:`SilhouetteReceiver` that skips, by their key and before decoding, silhouettes
    of rigs ``owns(rig)`` refuses (another replica estimates them), and remembers when each
    rig was last heard (to name a rig's owner)."""

    def __init__(self, session: zenoh.Session, *, owns: Callable[[str], bool], skipped: Counter,
                 **kwargs: Any) -> None:
        self._owns, self._skipped = owns, skipped
        self._heard: collections.OrderedDict[str, float] = collections.OrderedDict()
        self._heard_lock = threading.Lock()
        super().__init__(session, **kwargs)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        parts = str(sample.key_expr).split("/")
        if len(parts) == 4:  # posecal/<rig>/<camera>/silhouette (anything else: rejected below)
            rig = parts[1]
            with self._heard_lock:
                self._heard[rig] = time.monotonic()
                self._heard.move_to_end(rig)
                if len(self._heard) > _MAX_HEARD_RIGS:
                    self._heard.popitem(last=False)
            if not self._owns(rig):
                self._skipped.inc()
                return
        super()._on_sample(sample)

    def heard(self, within_s: float) -> list[str]:
        """Rigs whose silhouettes came within ``within_s`` seconds (any replica's), sorted."""
        now = time.monotonic()
        with self._heard_lock:
            return sorted(r for r, t in self._heard.items() if now - t <= within_s)

    def forget(self, rig: str) -> None:
        """Drop the agent epochs of ``rig``'s cameras: if the rig comes back, its runs are new."""
        with self._lock:
            for key in [k for k in self._epochs if k[0] == rig]:
                del self._epochs[key]


# ---------------------------------------------------------------------------- frame sets


@dataclass
class FrameSet:
    """One synchronized multi-camera frame (some cameras may be missing)."""

    index: int  # frame index (of the first message, for time-synchronised rigs)
    capture_ns: int
    created: float  # monotonic time the first message arrived
    parts: dict[str, SilhouetteMessage] = field(default_factory=dict)
    last_receive_ns: int = 0


class FrameAssembler:
    """Group one rig's messages into :class:`FrameSet` objects, emitted in order.

    Each camera's arrival lag behind the first camera of a frame set is learned
    (agents that started pacing at different moments stay offset by a constant
    delay); a frame set waits ``max_wait`` plus 1.5x the lag of the cameras it
    still misses, at most ``max_lag_s``. During the first ``max_wait`` after the
    rig's first message every frame set waits, so cameras that start together
    are all known before the first frame closes.
    """

    max_lag_s = 2.0

    def __init__(self, *, tolerance_ms: float, max_wait_ms: float, camera_timeout_s: float) -> None:
        self.tolerance_ns = int(tolerance_ms * 1e6)
        self.max_wait = max_wait_ms / 1e3
        self.camera_timeout = camera_timeout_s
        self.open: list[FrameSet] = []  # sorted by (index or capture time)
        self.last_seen: dict[str, float] = {}
        self.lag: dict[str, float] = {}
        self.last_closed: FrameSet | None = None
        self._closed_at: collections.OrderedDict[int, float] = collections.OrderedDict()
        self._started: float | None = None
        self.late = self.duplicate = self.missing = 0

    @staticmethod
    def _key(fs: FrameSet, by_index: bool) -> int:
        return fs.index if by_index else fs.capture_ns

    def _learn(self, cam: str, lag: float) -> None:
        old = self.lag.get(cam, lag)
        a = 0.5 if lag > old else 0.1  # learn a growing lag fast, forget it slowly
        self.lag[cam] = min(self.max_lag_s, old + a * (lag - old))

    def add(self, msg: SilhouetteMessage, receive_ns: int, now: float) -> list[FrameSet]:
        """Add one message; returns the frame sets it closed (in order)."""
        cam = msg.camera
        self.last_seen[cam] = now
        if self._started is None:
            self._started = now
        by_index = msg.sync == "index"
        key = msg.frame_index if by_index else msg.capture_ns
        tol = 0 if by_index else self.tolerance_ns
        if self.last_closed is not None and key <= self._key(self.last_closed, by_index) + tol:
            self.late += 1
            created = self._closed_at.get(key) if by_index else None
            self._learn(cam, now - (created if created is not None else self.last_closed.created))
            return self.poll(now)
        target = None
        for fs in self.open:
            if abs(self._key(fs, by_index) - key) <= tol:
                if cam in fs.parts:
                    if by_index or fs.parts[cam].frame_index == msg.frame_index:
                        self.duplicate += 1
                        return self.poll(now)
                    continue  # another frame of this camera within the tolerance
                target = fs
                break
        if target is None:
            target = FrameSet(msg.frame_index, msg.capture_ns, now)
            self.open.append(target)
            self.open.sort(key=lambda f: self._key(f, by_index))
        self._learn(cam, now - target.created)
        target.parts[cam] = msg
        target.last_receive_ns = max(target.last_receive_ns, receive_ns)
        return self.poll(now)

    def expected(self, now: float) -> set[str]:
        """Cameras heard from within the timeout."""
        return {c for c, t in self.last_seen.items() if now - t <= self.camera_timeout}

    def poll(self, now: float) -> list[FrameSet]:
        """Close the frame sets that are complete, overtaken or waited for long enough."""
        out: list[FrameSet] = []
        expected = self.expected(now)
        discovering = self._started is not None and now - self._started < self.max_wait
        while self.open:
            head = self.open[0]
            if discovering and now - head.created < self.max_wait:
                break
            later = set().union(*(fs.parts for fs in self.open[1:])) if len(self.open) > 1 else set()
            waiting = expected - set(head.parts) - later
            if waiting:
                wait = self.max_wait + 1.5 * max(self.lag.get(c, 0.0) for c in waiting)
                if now - head.created < min(wait, self.max_lag_s):
                    break
            self.open.pop(0)
            self.missing += len(expected - set(head.parts))
            self.last_closed = head
            self._closed_at[head.index] = head.created
            if len(self._closed_at) > 512:
                self._closed_at.popitem(last=False)
            out.append(head)
        return out


# ------------------------------------------------------------------------------ windows


@dataclass
class Window:
    """Frame sets handed to estimation."""

    rig: str
    seq: int
    frames: list[FrameSet]
    closed_ns: int  # arrival of the last message of the last frame set
    revision: int = 0  # estimated again since its first estimate (frames found to be another person's)
    other: dict[str, list[int]] = field(default_factory=dict)  # what its estimate left out (_on_another_person)

    @property
    def indices(self) -> list[int]:
        return [fs.index for fs in self.frames]


def _frame_period_s(frames: list[FrameSet]) -> float | None:
    """Median capture interval of consecutive frame sets (None if it cannot be told)."""
    t = np.array([fs.capture_ns for fs in frames], float)
    i = np.array([fs.index for fs in frames], float)
    step = np.diff(i)
    ok = step > 0
    if not ok.any():
        return None
    period = float(np.median(np.diff(t)[ok] / step[ok])) / 1e9
    return period if period > 0 else None


class WindowBuffer:
    """Cut sliding windows of ``length`` frame sets every ``hop``."""

    def __init__(self, length: int, hop: int) -> None:
        self.length, self.hop = length, hop
        self.frames: collections.deque[FrameSet] = collections.deque(maxlen=length)
        self._since = 0
        self._fresh = 0  # frames pushed since the last window or early look (take_fresh)
        self.resets = 0

    def push(self, fs: FrameSet) -> list[FrameSet] | None:
        """Add a frame set; returns a window's frames when one is due."""
        if self.frames and fs.index - self.frames[-1].index > self.length // 2:
            self.frames.clear()  # a long gap: the frames before belong to another walk
            self._fresh = 0
            self.resets += 1
        first = len(self.frames) < self.length
        self.frames.append(fs)
        self._since += 1
        self._fresh += 1
        if len(self.frames) == self.length and (first or self._since >= self.hop):
            self._since = self._fresh = 0
            return list(self.frames)
        return None

    def take_fresh(self, every: int) -> list[FrameSet] | None:
        """The frame sets pushed since the last window or the last call, once there are ``every``
        of them (0: never): what the next window will hold, to be looked at before it closes."""
        if every <= 0 or self._fresh < every:
            return None
        fresh, self._fresh = list(self.frames)[-self._fresh:], 0
        return fresh

    def clear(self) -> None:
        self.frames.clear()
        self._since = self._fresh = 0


# ------------------------------------------------------------------------------ rigs


@dataclass
class CameraState:
    frames: int = 0
    last_index: int = -1  # the rig's frame index of the camera's last frame (its own + index_offset)
    last_seen_ns: int = 0
    epoch_ns: int = 0
    sync: str = "time"
    image_size: tuple[int, int] = (0, 0)
    n_candidates: int | None = None  # person-sized components in the last frame (None: not reported)
    quality: Quality | None = None  # the agent's latest quality figures (sent every few frames)
    index_offset: int = 0  # added to this run's frame indices: non-zero once a restart was realigned
    last_capture_ns: int = 0
    period_ns: float | None = None  # capture time per frame index (moving average), to realign others
    # The agent's look back's moves: (run, track_id) -> the rig's frame index from which the earlier
    # tracks followed someone else (track_from; None: not said), oldest first, the last _MOVES kept.
    moves: dict[tuple[int, int], int | None] = field(default_factory=dict)

    def moved(self, msg: SilhouetteMessage) -> bool:
        """Keep the move ``msg`` (its indices the rig's) is the first message of; True when it is new
        and says from which frame (``track_from``)."""
        key = (msg.epoch_ns, msg.track_id)
        if not msg.track_id or key in self.moves:
            return False
        self.moves[key] = msg.track_from
        while len(self.moves) > _MOVES:
            del self.moves[next(iter(self.moves))]
        return msg.track_from is not None

    def observe(self, msg: SilhouetteMessage, receive_ns: int) -> None:
        """Count one message of the camera's current run (``msg.frame_index`` the rig's)."""
        step = msg.frame_index - self.last_index
        if self.frames and step > 0 and self.last_capture_ns and msg.epoch_ns == self.epoch_ns:
            period = (msg.capture_ns - self.last_capture_ns) / step
            if period > 0:
                old = self.period_ns
                self.period_ns = period if old is None else old + 0.1 * (period - old)
        self.frames += 1
        self.last_index, self.last_seen_ns, self.last_capture_ns = msg.frame_index, receive_ns, msg.capture_ns
        self.epoch_ns, self.sync, self.image_size = msg.epoch_ns, msg.sync, msg.image_size
        self.report(msg)

    def report(self, msg: SilhouetteMessage) -> None:
        """Keep what the agent reports about its segmentation (older agents report nothing)."""
        if msg.n_candidates is not None:
            self.n_candidates = msg.n_candidates
        if msg.quality is not None:
            self.quality = msg.quality

    def to_dict(self, *, age_s: float | None, stale: bool, in_windows: bool) -> dict[str, Any]:
        """The camera's entry in the rig summary (``schemas.CameraOut``)."""
        out = dataclasses.asdict(self)
        del out["last_capture_ns"], out["period_ns"]
        out["image_size"] = list(self.image_size)
        out.update(last_seen_s_ago=age_s, stale=stale, in_windows=in_windows)
        return out


_ONE_WALKER = "the papers assume one walker per rig: the tracked one is kept"
_MOVES = 32  # look-back moves kept per camera
_REVISABLE = 6  # estimated windows kept to be estimated again (a look back spans 45 frames: 4-5 windows)


def insert_by_seq(recent: collections.deque, result: dict[str, Any]) -> None:
    """Keep a rig's results in window order: with several live workers a window may finish
    after the next one. A result older than every kept one of a full history is dropped; a
    revision replaces its window's result."""
    seq = result["window"]["seq"]
    for i, r in enumerate(recent):
        if r["window"]["seq"] == seq:
            if result["window"].get("revision", 0) >= r["window"].get("revision", 0):
                recent[i] = result
            return
    i = len(recent)
    while i and recent[i - 1]["window"]["seq"] > seq:
        i -= 1
    if recent.maxlen is not None and len(recent) == recent.maxlen:
        if i == 0:
            return
        recent.popleft()
        i -= 1
    recent.insert(i, result)


def _cameras(frames: Iterable[FrameSet]) -> list[str]:
    """The cameras heard in any of ``frames``, sorted (a window's, and how its cameras are dealt)."""
    return sorted(set().union(*(fs.parts for fs in frames)))


def _on_another_person(frames: list[FrameSet], cam: str, moves: dict[tuple[int, int], int | None]) -> list[int]:
    """The indices of ``frames`` whose ``cam`` message followed someone else than the camera's walker:
    its agent has since moved the track (``moves``, :attr:`CameraState.moves`), so an earlier track's
    frames from the move's ``track_from`` on (the camera's own frame index), in any window, and all of
    an earlier track's frames in a window that holds frames of the later one (one person per window:
    before ``track_from`` the old track may have been on another walker)."""
    parts = [fs.parts.get(cam) for fs in frames]
    newest: dict[int, int] = {}  # run -> its newest track in these frames
    for m in parts:
        if m is not None and m.track_id is not None:
            newest[m.epoch_ns] = max(newest.get(m.epoch_ns, 0), m.track_id)
    return [fs.index for fs, m in zip(frames, parts) if m is not None and m.track_id is not None
            and any(run == m.epoch_ns and track > m.track_id
                    and (track <= newest[run] or (start is not None and m.frame_index >= start))
                    for (run, track), start in moves.items())]


def _others(frames: list[FrameSet], cams: list[str], moves: dict[str, dict]) -> dict[str, list[int]]:
    """Per camera of ``cams`` with any, :func:`_on_another_person` of ``frames`` with its ``moves``."""
    return {cam: other for cam in cams if (other := _on_another_person(frames, cam, moves.get(cam, {})))}


def _camera_tracks(frames: list[FrameSet], cams: list[str], other: dict[str, list[int]]) -> dict[str, CameraTrack]:
    """Each of ``cams``' track over ``frames`` (tight crops, full-frame boxes; None where it is missing
    and at the frames ``other`` lists for it, :func:`_others`)."""
    out = {}
    for cam in cams:
        left_out = set(other.get(cam, ()))
        out[cam] = track_from_segmentations([None if fs.index in left_out else fs.parts.get(cam) for fs in frames])
    return out


def window_keypoints(frames: list[FrameSet]) -> dict[str, np.ndarray] | None:
    """The keypoints the agents sent with a window's frames: camera -> (T, 13, 2), NaN where a frame
    has none; None when no camera sent any."""
    out = {}
    for cam in sorted(set().union(*(fs.parts for fs in frames))):
        sent = [None if (m := fs.parts.get(cam)) is None else m.keypoints for fs in frames]
        if any(k is not None for k in sent):
            out[cam] = np.stack([np.full((N_JOINTS, 2), np.nan) if k is None else k for k in sent])
    return out or None


def _crowd_notes(frames: list[FrameSet]) -> dict[str, str]:
    """Per camera whose agent saw several people in view in some of ``frames``, a note
    for the window's estimate (the agent sends the walker it tracks)."""
    crowded: dict[str, list[int]] = collections.defaultdict(list)
    for fs in frames:
        for cam, msg in fs.parts.items():
            if msg.n_candidates is not None and msg.n_candidates > 1:
                crowded[cam].append(msg.n_candidates)
    return {cam: f"several people in view in {len(n)} of {len(frames)} frames (up to {max(n)}): "
                 f"{_ONE_WALKER}" for cam, n in crowded.items()}


@dataclass
class RigState:
    """Everything the service knows about one rig."""

    name: str
    assembler: FrameAssembler
    buffer: WindowBuffer
    cameras: dict[str, CameraState] = field(default_factory=dict)
    recent: collections.deque = field(default_factory=collections.deque)
    tracks: dict[str, ViewpointTrack] = field(default_factory=dict)
    window_seq: int = 0
    estimated: int = 0
    skipped: int = 0
    failed: int = 0
    dropped: int = 0
    restarts: int = 0
    last_logged_index: int = -1
    priors_sent: int = 0
    feedback_lag_s: float | None = None  # last frame's capture to its window's priors published (EMA)
    publisher: Any = None
    feedback: dict[str, Any] = field(default_factory=dict)  # camera -> feedback publisher
    heard: dict[str, float] = field(default_factory=dict)  # camera -> monotonic time of its last frame
    rig_acc: Any = None  # estimator.rig.RigAccumulator: postures of recent windows (the live rig)
    calibration: dict | None = None  # the live rig's latest calibration (GET /v1/rigs/{rig}/calibration)
    moves_seen: int = 0  # camera moves detected so far: a new one restarts the live rig
    rig_generation: int = 0  # raised when the live rig restarts (postures measured before it are dropped)
    index_ahead: int = 0  # frames dropped: frame_index too far ahead of the rig
    realigned: int = 0  # restarted index-synchronised cameras re-based onto the rig's indices
    pending_ahead: dict[str, tuple[int, int]] = field(default_factory=dict)  # camera -> (index, run)
    before: WindowBefore | None = None  # the newest window estimated, for a look at the next (warm_every)
    done: collections.deque = field(default_factory=lambda: collections.deque(maxlen=_REVISABLE))  # Windows
    revised: int = 0  # windows estimated again (frames found to be another person's after their estimate)
    updates: int = 0  # results kept so far, first estimates and revisions (window.update)

    def moves(self) -> dict[str, dict[tuple[int, int], int | None]]:
        """A copy of every camera's look-back moves (:attr:`CameraState.moves`)."""
        return {name: dict(c.moves) for name, c in self.cameras.items()}

    def revisions(self, cam: str) -> list[Window]:
        """The estimated windows whose frames of ``cam`` another person's are now known to be more of
        than their estimate left out (a move of its agent's look back said so since), to be
        estimated again."""
        moves = self.cameras[cam].moves
        out = [w for w in self.done if _on_another_person(w.frames, cam, moves) != w.other.get(cam, [])]
        for w in out:
            self.done.remove(w)
        return [dataclasses.replace(w, revision=w.revision + 1) for w in out]

    def silent_for(self, now: float) -> float:
        """Seconds since any camera of the rig was heard from."""
        return now - max(self.heard.values(), default=now)

    def age(self, camera: str, now: float, timeout: float) -> tuple[float | None, bool]:
        """Seconds since ``camera``'s last frame (None if never heard) and whether it is stale
        (silent beyond ``timeout``: no longer waited for, its viewpoint no longer current)."""
        heard = self.heard.get(camera)
        if heard is None:
            return None, True
        age = max(0.0, now - heard)
        return round(age, 3), age > timeout

    def realign(self, msg: SilhouetteMessage, now: float, timeout: float) -> int | None:
        """The offset that puts a restarted index-synchronised camera's frame indices onto the
        rig's: the rig's index at ``msg.capture_ns``, from the newest frame of the other
        index-synchronised cameras heard within ``timeout`` and their frame period (without a
        period yet: their newest index); None when no other camera is live."""
        others = [c for name, c in self.cameras.items()
                  if name != msg.camera and c.sync == "index" and c.frames
                  and now - self.heard.get(name, -np.inf) <= timeout]
        if not others:
            return None
        ref = max(others, key=lambda c: c.last_index)
        index = ref.last_index
        periods = [c.period_ns for c in others if c.period_ns]
        if periods and ref.last_capture_ns:
            index += int(round((msg.capture_ns - ref.last_capture_ns) / float(np.median(periods))))
        return index - msg.frame_index

    def reference_index(self, msg: SilhouetteMessage, now: float, timeout: float) -> int | None:
        """The frame index ``msg`` is judged against: the newest of the rig's index-synchronised
        cameras heard within ``timeout`` (time-synchronised: the camera's own), None if none."""
        own = msg.sync != "index"
        refs = [c.last_index for name, c in self.cameras.items()
                if c.frames and now - self.heard.get(name, -np.inf) <= timeout
                and (name == msg.camera if own else c.sync == "index")]
        return max(refs, default=None)


class LiveService:
    """Subscribe, assemble, window, estimate, publish; thread-safe queries for the API."""

    def __init__(self, session: zenoh.Session, pool: PinnedPools, settings: Settings,
                 metrics: Metrics, rerun=None,
                 feedback_pool: concurrent.futures.Executor | None = None,
                 rig_pool: concurrent.futures.Executor | None = None,
                 replicas: Replicas | None = None) -> None:
        self.session, self.pool, self.settings = session, pool, settings
        self.replicas = replicas  # None: this service estimates every rig it hears
        self._owns = (lambda rig: True) if replicas is None else replicas.owns
        self.metrics, self.rerun = metrics, rerun
        self.feedback_pool = feedback_pool if settings.feedback else None
        self.rig_pool = rig_pool if settings.live_rig else None
        self._lock = threading.Lock()
        self._rigs: dict[str, RigState] = {}
        self._queue: queue.Queue[Window] = queue.Queue(maxsize=settings.queue_limit)
        self._stop = threading.Event()
        self._expired_at = time.monotonic()
        self._retired: list = []  # publishers of forgotten rigs and cameras, undeclared by _tick
        self._fresh: list = []  # frames of open windows for an early look (_look_early, by _tick)
        self._warming = 0  # early looks in the live workers
        self._estimating = 0  # windows in the live workers
        self._threads = [threading.Thread(target=self._consume, name=f"live-estimate-{i}", daemon=True)
                         for i in range(settings.live_workers)]
        self._threads.append(threading.Thread(target=self._tick, name="live-tick", daemon=True))
        self._rerun_queue: queue.Queue[tuple[str, StageBundle, int, dict]] = queue.Queue(maxsize=4)
        if rerun is not None:
            self._threads.append(threading.Thread(target=self._draw, name="live-rerun", daemon=True))
        # Newest window per rig whose priors are still to be made (an older one is superseded).
        self._feedback_todo: dict[str, tuple] = {}
        self._todo_ready = threading.Condition(self._lock)  # feedback and live-rig work waiting
        if self.feedback_pool is not None:
            self._threads.append(threading.Thread(target=self._feedback_loop, name="live-feedback",
                                                  daemon=True))
        self._rig_todo: dict[str, tuple] = {}  # newest window per rig whose postures are to be measured
        if self.rig_pool is not None:
            self._threads.append(threading.Thread(target=self._rig_loop, name="live-rig", daemon=True))
        for t in self._threads:
            t.start()
        self.receiver = _OwnedReceiver(session, owns=self._owns, skipped=metrics.frames_not_owned,
                                       on_message=self._on_message,
                                       max_clock_ahead_s=settings.max_clock_ahead_s,
                                       epoch_silence_s=settings.camera_timeout_s)
        metrics.watch_receiver(self.receiver.stats)
        metrics.watch_live(lambda: (len(self.rig_names()), len(replicas.alive()) if replicas else 1))
        if replicas is not None:
            replicas.on_change(self._rebalance)
            self._rebalance()  # the membership may have changed while this started

    # -- ingest (Zenoh callback thread) ---------------------------------------------------
    def _assembler(self) -> FrameAssembler:
        s = self.settings
        return FrameAssembler(tolerance_ms=s.sync_tolerance_ms, max_wait_ms=s.max_wait_ms,
                              camera_timeout_s=s.camera_timeout_s)

    def _rig(self, name: str) -> RigState:
        rig = self._rigs.get(name)
        if rig is None:
            s = self.settings
            rig = self._rigs[name] = RigState(name, self._assembler(), WindowBuffer(s.window_length, s.window_hop),
                                              recent=collections.deque(maxlen=s.history))
        return rig

    # -- admission: caps, expiry, plausible frame indices -----------------------------------
    def _admit(self, msg: SilhouetteMessage, now: float) -> RigState | None:
        """The message's rig, made if need be; None if a cap refuses it (counted)."""
        s = self.settings
        rig = self._rigs.get(msg.rig)
        if rig is None:
            if len(self._rigs) >= s.max_rigs and not self._make_room(now):
                self.metrics.live_refused.labels("rig_limit").inc()
                return None
            rig = self._rig(msg.rig)
        if msg.camera not in rig.cameras and len(rig.cameras) >= s.max_cameras:
            silent = [c for c in rig.cameras if now - rig.heard.get(c, -np.inf) > s.camera_timeout_s]
            if not silent:
                self.metrics.live_refused.labels("camera_limit").inc()
                return None
            self._forget_camera(rig, min(silent, key=lambda c: rig.heard.get(c, -np.inf)))
        return rig

    def _make_room(self, now: float) -> bool:
        """Forget the rig silent longest among those silent beyond ``camera_timeout_s``,
        rigs that never had a window estimated first; False if every rig is live."""
        silent = [r for r in self._rigs.values() if r.silent_for(now) > self.settings.camera_timeout_s]
        if not silent:
            return False
        self._forget_rig(min(silent, key=lambda r: (r.estimated > 0, -r.silent_for(now))))
        return True

    def _forget_rig(self, rig: RigState, *, handed_to: str | None = None) -> None:
        del self._rigs[rig.name]
        self._feedback_todo.pop(rig.name, None)
        self._rig_todo.pop(rig.name, None)  # a rig of the same name that comes back starts afresh
        self._retired += [rig.publisher, *rig.feedback.values()]
        self.metrics.forget_rig(rig.name, list(rig.cameras), handed_over=handed_to is not None)
        if handed_to is not None:
            log.info("rig %s handed over to replica %s", rig.name, handed_to)
        else:
            log.info("rig %s forgotten (silent %.0f s)", rig.name, rig.silent_for(time.monotonic()))

    def _rebalance(self) -> None:
        """After a change of replicas: drop the rigs another replica now estimates (their
        windows in flight are not published); rigs this one now owns start from their next
        frames, as new rigs."""
        with self._lock:
            moved = [rig for name, rig in self._rigs.items() if not self._owns(name)]
            for rig in moved:
                self._forget_rig(rig, handed_to=self.replicas.owner(rig.name))
        for rig in moved:
            self.receiver.forget(rig.name)

    def _forget_camera(self, rig: RigState, cam: str) -> None:
        for table in (rig.cameras, rig.heard, rig.tracks, rig.pending_ahead, rig.assembler.last_seen,
                      rig.assembler.lag):
            table.pop(cam, None)
        self._retired.append(rig.feedback.pop(cam, None))
        self.metrics.forget_camera(rig.name, cam)

    def _expire(self, now: float) -> None:
        """Forget rigs, and cameras of a rig, silent for ``rig_expiry_s`` (under the lock)."""
        limit = self.settings.rig_expiry_s
        for rig in list(self._rigs.values()):
            if rig.silent_for(now) > limit:
                self._forget_rig(rig)
                continue
            for cam in [c for c, t in rig.heard.items() if now - t > limit]:
                self._forget_camera(rig, cam)

    def _too_far_ahead(self, rig: RigState, msg: SilhouetteMessage, now: float) -> bool:
        """Whether ``msg`` is further than ``max_index_ahead`` ahead of its rig (drop it).

        One forged index far in the future would otherwise close a frame set
        there and make every later frame of the rig late. A rig that really
        jumped (a source that skipped) is followed once ``_REBASE_AFTER``
        consecutive frames of a camera agree with each other.
        """
        limit = self.settings.max_index_ahead
        ref = rig.reference_index(msg, now, self.settings.camera_timeout_s)
        if ref is None or msg.frame_index <= ref + limit:
            rig.pending_ahead.pop(msg.camera, None)
            return False
        last, run = rig.pending_ahead.get(msg.camera, (None, 0))
        run = run + 1 if last is not None and 0 < msg.frame_index - last <= limit else 1
        if run >= _REBASE_AFTER:
            rig.pending_ahead.pop(msg.camera, None)
            return False
        rig.pending_ahead[msg.camera] = (msg.frame_index, run)
        rig.index_ahead += 1
        return True

    def _on_message(self, item: Received) -> None:
        msg = item.message
        now = time.monotonic()
        with self._lock:
            if not self._owns(msg.rig):  # handed over since the receiver let it through
                return
            rig = self._admit(msg, now)
            if rig is None:
                return
            cam = rig.cameras.get(msg.camera)
            restarted = cam is not None and msg.epoch_ns != cam.epoch_ns  # indices start over
            offset = cam.index_offset if cam is not None else 0
            if restarted:  # None: start the rig's assembly over (time-synchronised, or alone)
                offset = rig.realign(msg, now, self.settings.camera_timeout_s) if msg.sync == "index" else None
                if offset is not None and msg.frame_index + offset < 0:  # a clock far behind the rig's
                    offset = None
            if offset:  # track_from with it: both are this run's frame indices
                msg = dataclasses.replace(msg, frame_index=msg.frame_index + offset, track_from=None
                                          if msg.track_from is None else max(0, msg.track_from + offset))
            if self._too_far_ahead(rig, msg, now):
                self.metrics.frames_dropped.labels(rig.name, "index_ahead").inc()
                return
            if restarted:
                rig.restarts += 1
                cam.index_offset = offset or 0
                if offset is None:  # no other camera live: the rig's assembly starts over
                    rig.assembler = self._assembler()
                    rig.buffer.clear()
                    rig.before = None
                else:  # joined onto the rig's frames; its lag is learned anew
                    rig.realigned += 1
                    rig.assembler.lag.pop(msg.camera, None)
                    log.info("%s/%s restarted at frame %d: re-based onto the rig's frame %d",
                             rig.name, msg.camera, msg.frame_index - offset, msg.frame_index)
            if cam is None:
                cam = rig.cameras[msg.camera] = CameraState()
            rig.heard[msg.camera] = now
            cam.observe(msg, item.receive_ns)
            moved = cam.moved(msg)
            before = (rig.assembler.late, rig.assembler.duplicate, rig.assembler.missing)
            closed = rig.assembler.add(msg, item.receive_ns, now)
            self._count_drops(rig, before)
            windows = self._windows(rig, closed) + (rig.revisions(msg.camera) if moved else [])
        self.metrics.frames_in.labels(msg.rig, msg.camera).inc()
        for w in windows:
            self._enqueue(w)

    def _count_drops(self, rig: RigState, before: tuple[int, int, int]) -> None:
        a = rig.assembler
        late, dup, miss = a.late - before[0], a.duplicate - before[1], a.missing - before[2]
        if late:
            self.metrics.frames_dropped.labels(rig.name, "late").inc(late)
        if dup:
            self.metrics.frames_dropped.labels(rig.name, "duplicate").inc(dup)
        if miss:
            self.metrics.frames_missing.labels(rig.name).inc(miss)

    def _windows(self, rig: RigState, closed: list[FrameSet]) -> list[Window]:
        out = []
        for fs in closed:
            frames = rig.buffer.push(fs)
            if frames is not None:
                rig.window_seq += 1
                out.append(Window(rig.name, rig.window_seq, frames, max(f.last_receive_ns for f in frames)))
            elif (fresh := rig.buffer.take_fresh(self.settings.warm_every)) is not None:
                cams = _cameras(rig.buffer.frames)  # as the window's will be
                self._fresh.append((rig.name, fresh, cams, rig.before, rig.window_seq))
        return out

    def _look_early(self, fresh: list[tuple[str, list[FrameSet], list[str], WindowBefore | None, int]]) -> None:
        """Frames of windows not yet closed registered and matched by the processes that will
        estimate them, at the rig's newest window's viewpoints and phase
        (:func:`~service.worker.warm_window`), so that a window waits on its last frames only.
        In the live workers' idle time only: skipped while a window is estimated or waits (it
        will do the same work when it closes, and the window in hand comes first)."""
        for name, frames, cams, before, seq in fresh:
            with self._lock:
                rig = self._rigs.get(name)
                busy = self._queue.qsize() or self._estimating or self._warming >= len(self.pool)
                go = not busy and rig is not None and rig.window_seq == seq  # else a window holds them now
                if go:
                    self._warming += 1
                    moves = rig.moves()
            if not go:
                self.metrics.frames_warmed.labels("skipped").inc(len(frames))
                continue
            try:
                tracks = _camera_tracks(frames, cams, _others(frames, cams, moves))
                future = warm_window(self.pool, name, tracks, [fs.index for fs in frames], before)
            except Exception:  # noqa: BLE001 - a look is never worth the tick thread: its window will do it
                log.exception("early look at %s frames %d-%d failed", name, frames[0].index, frames[-1].index)
                self._warmed(None)
                continue
            self.metrics.frames_warmed.labels("sent").inc(len(frames))
            future.add_done_callback(self._warmed)

    def _warmed(self, future: concurrent.futures.Future | None) -> None:
        with self._lock:
            self._warming -= 1
        if future is not None and (future.cancelled() or future.exception() is not None):
            log.debug("early look failed or cancelled (its window will do it: nothing lost but time)")

    def _tick(self) -> None:
        """Close frame sets whose missing cameras did not come in time; forget silent rigs."""
        while not self._stop.wait(0.01):
            now = time.monotonic()
            windows = []
            with self._lock:
                if now - self._expired_at > _EXPIRE_EVERY_S:
                    self._expired_at = now
                    self._expire(now)
                retired, self._retired = self._retired, []
                for rig in self._rigs.values():
                    before = (rig.assembler.late, rig.assembler.duplicate, rig.assembler.missing)
                    closed = rig.assembler.poll(now)
                    if closed:
                        self._count_drops(rig, before)
                        windows += self._windows(rig, closed)
                fresh, self._fresh = self._fresh, []
            for pub in retired:
                _undeclare(pub)
            for w in windows:
                self._enqueue(w)
            self._look_early(fresh)  # after the windows: a look never goes ahead of one

    def _enqueue(self, w: Window) -> None:
        while True:
            try:
                self._queue.put_nowait(w)
                return
            except queue.Full:
                try:
                    old = self._queue.get_nowait()
                except queue.Empty:
                    continue
                self._count(old, "dropped")

    def _count(self, w: Window, outcome: str) -> None:
        """Window ``w`` ended as ``outcome`` (skipped, failed, dropped): state and metric. Not for a
        revision: its window was counted estimated, and its first estimate stands."""
        if w.revision:
            return
        rig = w.rig
        with self._lock:
            state = self._rigs.get(rig)
            if state is None:  # forgotten meanwhile: its metrics are gone too
                return
            setattr(state, outcome, getattr(state, outcome) + 1)
        self.metrics.windows.labels(rig, outcome).inc()

    # -- estimation (consumer threads) ------------------------------------------------------
    def _consume(self) -> None:
        while not self._stop.is_set():
            try:
                w = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            with self._lock:
                self._estimating += 1  # from here: no early look goes ahead of this window
            try:
                self._process(w)
            except Exception:  # keep the consumer alive; the window counts as failed
                log.exception("window %s/%d failed", w.rig, w.seq)
                self._count(w, "failed")
            finally:
                with self._lock:
                    self._estimating -= 1

    def _tracks(self, w: Window, cams: list[str], other: dict[str, list[int]]
                ) -> tuple[dict[str, CameraTrack], dict[str, tuple[int, int]]] | None:
        present = 0
        for fs in w.frames:
            present += any(not m.box.empty for m in fs.parts.values())
        if present < max(1, self.settings.min_present * len(w.frames)):
            return None
        sizes = {cam: next(fs.parts[cam].image_size for fs in reversed(w.frames) if cam in fs.parts) for cam in cams}
        return _camera_tracks(w.frames, cams, other), sizes

    def _process(self, w: Window) -> None:
        with self._lock:
            rig = self._rigs.get(w.rig)
            if rig is None:  # forgotten or handed over while it waited
                return
            moves = rig.moves()
            earlier = earlier_azimuths(rig.tracks, self.settings.fold_windows)
        cams = _cameras(w.frames)
        other = _others(w.frames, cams, moves)
        built = self._tracks(w, cams, other)
        if built is None:
            self._count(w, "skipped")
            return
        tracks, sizes = built
        bundle_from = None
        if self.rerun is not None:
            with self._lock:
                rig = self._rigs.get(w.rig)
                last = -1 if rig is None else rig.last_logged_index
            bundle_from = sum(1 for i in w.indices if i <= last)
        feedback = self.feedback_pool is not None
        try:
            result, bundle, seconds, est = estimate_window(self.pool, w.rig, tracks, w.indices, sizes,
                                                           bundle_from=bundle_from,
                                                           in_flight=self.settings.live_workers,
                                                           earlier=earlier)
        except ValueError as exc:  # nothing estimable (e.g. no silhouette matched)
            log.info("window %s/%d not estimated: %s", w.rig, w.seq, exc)
            self._count(w, "skipped")
            return
        revised = w.revision > 0
        with self._lock:
            rig = self._rigs.get(w.rig)
            if rig is None:  # forgotten while its window was estimated
                return
            smoothed = {}
            for cam, c in result["cameras"].items():
                track = rig.tracks.get(cam)
                if track is None:
                    track = rig.tracks[cam] = ViewpointTrack(
                        threshold_deg=self.settings.change_threshold_deg,
                        confirm=self.settings.change_windows, settle=self.settings.change_windows)
                # A revision leaves the smoothing as it is (its first estimate went in: docs/SERVICE.md).
                smoothed[cam] = track.state() if revised else track.update(
                    own_azimuth(c["azimuth_deg"], c["flip"]), c["elevation_deg"], w.indices[-1])
            if not revised and (rig.before is None or w.seq > rig.before.seq):  # windows may finish out of order
                rig.before = WindowBefore.of(w.seq, w.indices, est)
            # A move of an agent's look back heard while this was estimated may have more frames to leave out.
            w = dataclasses.replace(w, other=other)
            again = [] if _others(w.frames, cams, rig.moves()) == other else [
                dataclasses.replace(w, revision=w.revision + 1)]
            if not again:
                rig.done.append(w)
            publisher = rig.publisher
            if publisher is None:
                publisher = rig.publisher = self.session.declare_publisher(estimate_key(w.rig))
            cal = rig.calibration
            person = None if cal is None or not cal.get("person") else {
                **cal["person"], "window_seq": cal["window_seq"], "lag_windows": max(0, w.seq - cal["window_seq"])}
        for cam, note in _crowd_notes(w.frames).items():
            if cam in result["cameras"]:
                result["cameras"][cam].setdefault("notes", []).append(note)
        done_ns = time.time_ns()
        latency = max(0.0, (done_ns - w.closed_ns) / 1e9)
        result.update({
            "rig": w.rig,
            "window": {"seq": w.seq, "first_index": w.indices[0], "last_index": w.indices[-1],
                       "frames": len(w.frames), "cameras": sorted(tracks),
                       # the window's frames that lack a camera's message (no frame of it lost unseen)
                       "missing": {cam: gaps for cam in sorted(tracks)
                                   if (gaps := [fs.index for fs in w.frames if cam not in fs.parts])},
                       "other_person": {cam: other[cam] for cam in sorted(tracks) if cam in other},
                       "revision": w.revision},
            "smoothed": smoothed,
            "latency_ms": {"estimate": round(seconds * 1e3, 2), "last_frame_to_result": round(latency * 1e3, 2)},
            "published_ns": done_ns,
        })
        if person is not None:  # the live rig's newest posture of the person, with how far it lags
            result["person"] = person
        with self._lock:  # stamped and kept at once: a client polling by update misses none
            rig.updates += 1
            result["window"]["update"] = rig.updates
            insert_by_seq(rig.recent, result)
            if revised:
                rig.revised += 1
            else:
                rig.estimated += 1
                rig.last_logged_index = max(rig.last_logged_index, w.indices[-1])
        # The attachment names the replica that estimated it (the result itself stays as documented).
        publisher.put(json.dumps(result, separators=(",", ":")), attachment=self.settings.replica_id)
        self.metrics.window_estimate.observe(seconds)
        self.metrics.windows.labels(w.rig, "revised" if revised else "estimated").inc()
        for revision in again:
            self._enqueue(revision)
        if revised:  # its first estimate drew, made priors and fed the live rig
            return
        self.metrics.window_latency.observe(latency)
        if self.rerun is not None and bundle is not None:
            try:
                self._rerun_queue.put_nowait((w.rig, bundle, w.indices[-1], smoothed))
            except queue.Full:  # drawing fell behind: skip this window's drawing, not its estimate
                self.metrics.rerun_skipped.labels(w.rig).inc()
        if feedback:
            with self._lock:
                if w.rig in self._feedback_todo:
                    self.metrics.feedback_superseded.labels(w.rig).inc()
                self._feedback_todo[w.rig] = (w, est, tracks, sizes)
                self._todo_ready.notify_all()  # both loops wait on it
        if self.rig_pool is not None:
            moves = sum(len(sm.get("changes", [])) for sm in smoothed.values())
            with self._lock:
                if moves > rig.moves_seen:  # a camera moved: the rig is another one
                    rig.moves_seen, rig.rig_acc, rig.calibration = moves, None, None
                    rig.rig_generation += 1
                self._rig_todo[w.rig] = (w, est)  # supersedes an older window not yet measured
                self._todo_ready.notify_all()

    def _feedback_loop(self) -> None:
        """Make and publish priors, newest window of each rig first; never blocks estimation."""
        self._newest_first(self._feedback_todo, self._feedback, "feedback priors")

    def _rig_loop(self) -> None:
        """Measure postures of the newest window of each rig and recalibrate its rig now and then,
        in the low-priority rig process; a window that comes while one is measured supersedes the
        one waiting (the rig lags the viewpoints by a window or so, see ``calibration``)."""
        self._newest_first(self._rig_todo, self._update_rig, "live rig")

    def _newest_first(self, todo: dict[str, tuple], handle, what: str) -> None:
        """Until close(): take a rig's waiting job from ``todo`` (rig -> arguments, newest only) and
        ``handle(*arguments)`` it; a failure is logged and loses that window's work only."""
        while True:
            with self._lock:
                while not todo and not self._stop.is_set():
                    self._todo_ready.wait(timeout=0.1)
                if self._stop.is_set():
                    return
                rig = next(iter(todo))
                job = todo.pop(rig)
            try:
                handle(*job)
            except Exception:  # keep the loop alive
                log.exception("%s for %s failed", what, rig)

    def _result(self, future: concurrent.futures.Future, timeout_s: float):
        """The future's result, waited for in slices so that close() need not wait for it;
        None (and the call cancelled) on close or after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                return future.result(timeout=0.1)
            except concurrent.futures.TimeoutError:
                if self._stop.is_set() or time.monotonic() > deadline:
                    future.cancel()
                    return None

    def _update_rig(self, w: Window, est) -> None:
        from estimator.rig import RigAccumulator, RigConfig

        from .worker import update_rig

        s = self.settings
        with self._lock:
            rig = self._rigs.get(w.rig)
            if rig is None:
                return
            acc = rig.rig_acc or RigAccumulator(RigConfig(height_m=s.live_rig_height_m),
                                                frames_per_window=s.live_rig_frames)
            calibrate = (acc.windows + 1) % s.live_rig_every == 0 or rig.calibration is None
            generation = rig.rig_generation
            # the viewpoints over every window so far, not only the few the rig process measured
            views = {cam: (v["azimuth_deg"], v["elevation_deg"]) for cam, t in rig.tracks.items()
                     if (v := t.state())["azimuth_deg"] is not None}
        t0 = time.perf_counter()
        done = self._result(self.rig_pool.submit(update_rig, acc, est, w.indices, calibrate,
                                                 window_keypoints(w.frames), views), 120)
        if done is None:
            return
        acc, cal, cameras = done
        self.metrics.rig_seconds.observe(time.perf_counter() - t0)
        with self._lock:
            if self._rigs.get(w.rig) is not rig or rig.rig_generation != generation:
                return  # forgotten, or a camera moved while this was measured
            rig.rig_acc = acc
            if cal is not None:
                rig.calibration = {"rig": w.rig, "window_seq": w.seq, "last_index": w.indices[-1],
                                   "updated_ns": time.time_ns(), **cal}
        ref = est.cameras.get(cameras["reference"]) if cameras is not None else None
        if self.rerun is not None and ref is not None:  # placed through this window's reference viewpoint
            self.rerun.log_rig(f"rigs/{w.rig}", w.indices[-1], cameras,
                               (ref.viewpoint.azimuth_deg, ref.viewpoint.elevation_deg))

    def _feedback(self, w: Window, est, tracks: dict[str, CameraTrack],
                  sizes: dict[str, tuple[int, int]]) -> None:
        """Render and publish priors for the next frames of every camera (§7.1).

        Each prior names the agent run (epoch) whose frame indices it predicts,
        so a restarted agent ignores it; the agent checks it against its own
        evidence before use (``capture.segment``).
        """
        t0 = time.perf_counter()
        with self._lock:
            rig = self._rigs.get(w.rig)
            if rig is None:
                return
            lag_s = rig.feedback_lag_s
        # Frames captured before these priors can arrive need none: skip them.
        period_s = _frame_period_s(w.frames)
        skip = 0 if period_s is None or lag_s is None else int(lag_s / period_s)
        priors = self._result(self.feedback_pool.submit(predict_feedback, est, tracks, w.indices, sizes,
                                                        self.settings.feedback_ahead, skip), 60)
        if priors is None:
            return
        # The run whose frame indices the window holds (not a run that started since).
        epochs = {cam: m.epoch_ns for fs in w.frames for cam, m in fs.parts.items()}
        with self._lock:
            if self._stop.is_set() or self._rigs.get(w.rig) is not rig:
                return
            # A realigned camera's priors name its own frame indices, not the rig's.
            offsets = {cam: c.index_offset for cam, c in rig.cameras.items() if c.epoch_ns == epochs.get(cam)}
            publishers = {}
            for cam in priors:
                pub = rig.feedback.get(cam)
                if pub is None:
                    pub = rig.feedback[cam] = self.session.declare_publisher(
                        feedback_key(w.rig, cam), congestion_control=zenoh.CongestionControl.DROP,
                        express=True)
                publishers[cam] = pub
        sent = 0
        for cam, items in priors.items():
            for index, box, mask in items:
                msg = FeedbackMessage(rig=w.rig, camera=cam, frame_index=index - offsets.get(cam, 0), box=Box(*box),
                                      image_size=sizes[cam], mask=mask, issued_ns=time.time_ns(),
                                      epoch_ns=epochs.get(cam, 0))
                publishers[cam].put(encode(msg))
                sent += 1
        self.metrics.feedback_priors.labels(w.rig).inc(sent)
        self.metrics.feedback_seconds.observe(time.perf_counter() - t0)
        lag = (time.time_ns() - w.frames[-1].capture_ns) / 1e9  # last frame captured -> priors out
        with self._lock:
            rig.priors_sent += sent
            if 0 <= lag < 10:  # a moving average of what the next window's priors will take,
                # from the first lag measured (an average started at 0 s underestimates it
                # for the first windows, whose priors then name frames already captured)
                old = rig.feedback_lag_s
                rig.feedback_lag_s = lag if old is None else old + 0.3 * (lag - old)
        if self.rerun is not None and priors:
            self.rerun.log_priors(f"rigs/{w.rig}", priors)

    def _draw(self) -> None:
        """Rerun logging, off the estimation path: registration in the pool, then log."""
        while not self._stop.is_set() or not self._rerun_queue.empty():
            try:
                rig, bundle, last, smoothed = self._rerun_queue.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                bundle = self.pool.submit(register_stage, bundle).result(timeout=60)
                self.rerun.log_window(f"rigs/{rig}", bundle)
                self.rerun.log_smoothed(f"rigs/{rig}", last, smoothed)
            except Exception:
                log.exception("drawing window of %s failed", rig)

    # -- queries (API threads) -------------------------------------------------------------
    def rig_names(self) -> list[str]:
        with self._lock:
            return sorted(self._rigs)

    def summary(self, name: str) -> dict[str, Any] | None:
        with self._lock:
            rig = self._rigs.get(name)
            if rig is None:
                return None
            a = rig.assembler
            latest = rig.recent[-1] if rig.recent else None
            now, timeout = time.monotonic(), self.settings.camera_timeout_s
            current = set(latest["window"]["cameras"]) if latest is not None else set()
            ages = {c: rig.age(c, now, timeout) for c in set(rig.cameras) | set(rig.tracks)}
            return {
                "rig": rig.name,
                "cameras": {c: s.to_dict(age_s=ages[c][0], stale=ages[c][1], in_windows=c in current)
                            for c, s in sorted(rig.cameras.items())},
                "windows": {"seq": rig.window_seq, "estimated": rig.estimated, "skipped": rig.skipped,
                            "failed": rig.failed, "dropped": rig.dropped, "revised": rig.revised},
                "feedback": {"enabled": self.feedback_pool is not None, "priors_sent": rig.priors_sent},
                "frames": {"late": a.late, "duplicate": a.duplicate, "missing": a.missing,
                           "restarts": rig.restarts, "realigned": rig.realigned, "gaps": rig.buffer.resets,
                           "index_ahead": rig.index_ahead},
                "viewpoints": {c: {**t.state(), "last_seen_s_ago": ages[c][0], "stale": ages[c][1]}
                               for c, t in sorted(rig.tracks.items())},
                "latest_seq": None if latest is None else latest["window"]["seq"],
            }

    def latest(self, name: str) -> dict | None:
        with self._lock:
            rig = self._rigs.get(name)
            return None if rig is None or not rig.recent else rig.recent[-1]

    def since(self, name: str, seq: int, limit: int, *, updated_since: int | None = None) -> list[dict] | None:
        """The kept results with window ``seq`` greater than ``seq``, in window order; with
        ``updated_since``, those kept (first estimates and revisions) after that ``update``, in
        the order they were kept."""
        with self._lock:
            rig = self._rigs.get(name)
            if rig is None:
                return None
            if updated_since is None:
                return [r for r in rig.recent if r["window"]["seq"] > seq][:limit]
            return sorted((r for r in rig.recent if r["window"]["update"] > updated_since),
                          key=lambda r: r["window"]["update"])[:limit]

    def calibration(self, name: str) -> dict | None:
        """The live rig's latest calibration with how many windows it lags the estimates; None
        before the first (or since a camera moved)."""
        with self._lock:
            rig = self._rigs.get(name)
            if rig is None or rig.calibration is None:
                return None
            return {**rig.calibration, "lag_windows": max(0, rig.window_seq - rig.calibration["window_seq"])}

    def has_rig(self, name: str) -> bool:
        with self._lock:
            return name in self._rigs

    def estimated_by(self, name: str) -> str | None:
        """The other replica that estimates rig ``name``, if the rig is heard on the network
        (within ``rig_expiry_s``) and not estimated here; else None."""
        if self.replicas is None or self._owns(name) or name not in self.receiver.heard(self.settings.rig_expiry_s):
            return None
        return self.replicas.owner(name)

    def replica_view(self) -> dict[str, Any]:
        """This replica, and per alive replica the rigs heard within ``rig_expiry_s`` that it
        estimates, as seen from here (``GET /v1/replicas``)."""
        me = self.settings.replica_id
        heard = self.receiver.heard(self.settings.rig_expiry_s)
        if self.replicas is None:
            return {"replica": me, "enabled": False, "active": True, "others_with_this_id": [],
                    "replicas": [{"replica": me, "rigs": heard}]}
        rigs: dict[str, list[str]] = {r: [] for r in self.replicas.alive()}
        for rig in heard:
            rigs.setdefault(self.replicas.owner(rig), []).append(rig)
        return {"replica": me, "enabled": True, "active": self.replicas.active,
                "others_with_this_id": self.replicas.sessions().get(me, []),
                "replicas": [{"replica": r, "rigs": owned} for r, owned in sorted(rigs.items())]}

    def close(self) -> None:
        self._stop.set()
        try:
            self.receiver.close()
        except Exception:  # the session may already be closed
            pass
        for t in self._threads:
            t.join(timeout=5)
        with self._lock:
            for rig in self._rigs.values():
                for pub in [rig.publisher, *rig.feedback.values()]:
                    _undeclare(pub)


def _undeclare(publisher) -> None:
    """Undeclare a Zenoh publisher (None: nothing), whatever state the session is in."""
    if publisher is None:
        return
    try:
        publisher.undeclare()
    except Exception:  # the session may already be closed
        pass
