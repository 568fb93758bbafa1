"""Live estimation: silhouettes from Zenoh -> synchronized frames -> sliding windows -> estimates.

Per rig:

1. :class:`FrameAssembler` groups the cameras' messages into frame sets: by
   ``frame_index`` when the agents say ``sync="index"`` (hardware-triggered or
   synthetic rigs), else by ``capture_ns`` within ``sync_tolerance_ms``. A frame
   set is closed when every expected camera is in it or has already sent a later
   frame (Zenoh keeps each publisher's order), or after ``max_wait_ms``; missing
   cameras then count as "no data". Late messages (for a closed frame) and
   duplicates are dropped and counted. A camera silent for ``camera_timeout_s``
   is no longer waited for; an agent restart (new epoch) resets the rig.
2. :class:`WindowBuffer` cuts windows of ``window_length`` frame sets every
   ``window_hop``; a jump in frame index larger than half a window starts over.
3. Windows wait in a bounded queue (oldest dropped on overflow); consumer
   threads send each to the process pool (:func:`service.worker.estimate_window`),
   smooth the viewpoints (:class:`estimator.windows.ViewpointTrack`), publish the result on
   ``posecal/<rig>/estimate``, keep it for the REST API and log it to Rerun.
4. Feedback (§7.1, ``feedback``): the window's estimate predicts the next
   ``feedback_ahead`` frames of every camera; their rendered, registered priors
   go to ``posecal/<rig>/<camera>/feedback`` ahead of the frames they are for.

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
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zenoh

from capture.receiver import Received, SilhouetteReceiver
from capture.wire import Box, FeedbackMessage, Quality, SilhouetteMessage, encode, estimate_key, feedback_key
from capture.refine import track_from_segmentations
from estimator.pipeline import CameraTrack
from estimator.windows import ViewpointTrack

from .metrics import Metrics
from .settings import Settings
from .worker import StageBundle, estimate_window, predict_feedback, register_stage

__all__ = ["FrameAssembler", "FrameSet", "LiveService", "WindowBuffer"]

log = logging.getLogger(__name__)


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
        self.resets = 0

    def push(self, fs: FrameSet) -> list[FrameSet] | None:
        """Add a frame set; returns a window's frames when one is due."""
        if self.frames and fs.index - self.frames[-1].index > self.length // 2:
            self.frames.clear()  # a long gap: the frames before belong to another walk
            self.resets += 1
        first = len(self.frames) < self.length
        self.frames.append(fs)
        self._since += 1
        if len(self.frames) == self.length and (first or self._since >= self.hop):
            self._since = 0
            return list(self.frames)
        return None

    def clear(self) -> None:
        self.frames.clear()
        self._since = 0


# ------------------------------------------------------------------------------ rigs


@dataclass
class CameraState:
    frames: int = 0
    last_index: int = -1
    last_seen_ns: int = 0
    epoch_ns: int = 0
    sync: str = "time"
    image_size: tuple[int, int] = (0, 0)
    n_candidates: int | None = None  # person-sized components in the last frame (None: not reported)
    quality: Quality | None = None  # the agent's latest quality figures (sent every few frames)

    def report(self, msg: SilhouetteMessage) -> None:
        """Keep what the agent reports about its segmentation (older agents report nothing)."""
        if msg.n_candidates is not None:
            self.n_candidates = msg.n_candidates
        if msg.quality is not None:
            self.quality = msg.quality

    def to_dict(self) -> dict[str, Any]:
        """The camera's entry in the rig summary (``schemas.CameraOut``)."""
        out = dataclasses.asdict(self)
        out["image_size"] = list(self.image_size)
        return out


_ONE_WALKER = "the papers assume one walker per rig: the tracked one is kept"


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


class LiveService:
    """Subscribe, assemble, window, estimate, publish; thread-safe queries for the API."""

    def __init__(self, session: zenoh.Session, pool: concurrent.futures.Executor, settings: Settings,
                 metrics: Metrics, rerun=None,
                 feedback_pool: concurrent.futures.Executor | None = None) -> None:
        self.session, self.pool, self.settings = session, pool, settings
        self.metrics, self.rerun = metrics, rerun
        self.feedback_pool = feedback_pool if settings.feedback else None
        self._lock = threading.Lock()
        self._rigs: dict[str, RigState] = {}
        self._queue: queue.Queue[Window] = queue.Queue(maxsize=settings.queue_limit)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._consume, name=f"live-estimate-{i}", daemon=True)
                         for i in range(settings.live_workers)]
        self._threads.append(threading.Thread(target=self._tick, name="live-tick", daemon=True))
        self._rerun_queue: queue.Queue[tuple[str, StageBundle, int, dict]] = queue.Queue(maxsize=4)
        if rerun is not None:
            self._threads.append(threading.Thread(target=self._draw, name="live-rerun", daemon=True))
        # Newest window per rig whose priors are still to be made (an older one is superseded).
        self._feedback_todo: dict[str, tuple] = {}
        self._feedback_ready = threading.Condition(self._lock)
        if self.feedback_pool is not None:
            self._threads.append(threading.Thread(target=self._feedback_loop, name="live-feedback",
                                                  daemon=True))
        for t in self._threads:
            t.start()
        self.receiver = SilhouetteReceiver(session, on_message=self._on_message)
        metrics.watch_receiver(self.receiver.stats)

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

    def _on_message(self, item: Received) -> None:
        msg = item.message
        now = time.monotonic()
        with self._lock:
            rig = self._rig(msg.rig)
            cam = rig.cameras.get(msg.camera)
            if item.new_epoch and cam is not None:  # an agent restarted: frame indices start over
                rig.restarts += 1
                rig.assembler = self._assembler()
                rig.buffer.clear()
            if cam is None:
                cam = rig.cameras[msg.camera] = CameraState()
            cam.frames += 1
            cam.last_index, cam.last_seen_ns = msg.frame_index, item.receive_ns
            cam.epoch_ns, cam.sync, cam.image_size = msg.epoch_ns, msg.sync, msg.image_size
            cam.report(msg)
            before = (rig.assembler.late, rig.assembler.duplicate, rig.assembler.missing)
            closed = rig.assembler.add(msg, item.receive_ns, now)
            self._count_drops(rig, before)
            windows = self._windows(rig, closed)
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
        return out

    def _tick(self) -> None:
        """Close frame sets whose missing cameras did not come in time."""
        while not self._stop.wait(0.01):
            now = time.monotonic()
            windows = []
            with self._lock:
                for rig in self._rigs.values():
                    before = (rig.assembler.late, rig.assembler.duplicate, rig.assembler.missing)
                    closed = rig.assembler.poll(now)
                    if closed:
                        self._count_drops(rig, before)
                        windows += self._windows(rig, closed)
            for w in windows:
                self._enqueue(w)

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
                self._count(old.rig, "dropped")

    def _count(self, rig: str, outcome: str) -> None:
        """One window of ``rig`` ended as ``outcome`` (skipped, failed, dropped): state and metric."""
        with self._lock:
            state = self._rigs[rig]
            setattr(state, outcome, getattr(state, outcome) + 1)
        self.metrics.windows.labels(rig, outcome).inc()

    # -- estimation (consumer threads) ------------------------------------------------------
    def _consume(self) -> None:
        while not self._stop.is_set():
            try:
                w = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            try:
                self._process(w)
            except Exception:  # keep the consumer alive; the window counts as failed
                log.exception("window %s/%d failed", w.rig, w.seq)
                self._count(w.rig, "failed")

    def _tracks(self, w: Window) -> tuple[dict[str, CameraTrack], dict[str, tuple[int, int]]] | None:
        cams = sorted(set().union(*(fs.parts for fs in w.frames)))
        tracks, sizes = {}, {}
        present = 0
        for fs in w.frames:
            present += any(not m.box.empty for m in fs.parts.values())
        if present < max(1, self.settings.min_present * len(w.frames)):
            return None
        for cam in cams:
            parts = [fs.parts.get(cam) for fs in w.frames]
            tracks[cam] = track_from_segmentations(parts)
            sizes[cam] = next(m.image_size for m in reversed(parts) if m is not None)
        return tracks, sizes

    def _process(self, w: Window) -> None:
        built = self._tracks(w)
        if built is None:
            self._count(w.rig, "skipped")
            return
        tracks, sizes = built
        bundle_from = None
        if self.rerun is not None:
            with self._lock:
                last = self._rigs[w.rig].last_logged_index
            bundle_from = sum(1 for i in w.indices if i <= last)
        feedback = self.feedback_pool is not None
        future = self.pool.submit(estimate_window, tracks, w.indices, sizes, bundle_from=bundle_from,
                                  keep_estimate=feedback)
        try:
            result, bundle, seconds, est = future.result(timeout=60)
        except ValueError as exc:  # nothing estimable (e.g. no silhouette matched)
            log.info("window %s/%d not estimated: %s", w.rig, w.seq, exc)
            self._count(w.rig, "skipped")
            return
        with self._lock:
            rig = self._rigs[w.rig]
            smoothed = {}
            for cam, c in result["cameras"].items():
                track = rig.tracks.get(cam)
                if track is None:
                    track = rig.tracks[cam] = ViewpointTrack(
                        threshold_deg=self.settings.change_threshold_deg,
                        confirm=self.settings.change_windows)
                smoothed[cam] = track.update(c["azimuth_deg"], c["elevation_deg"], w.indices[-1])
            publisher = rig.publisher
            if publisher is None:
                publisher = rig.publisher = self.session.declare_publisher(estimate_key(w.rig))
        for cam, note in _crowd_notes(w.frames).items():
            if cam in result["cameras"]:
                result["cameras"][cam].setdefault("notes", []).append(note)
        done_ns = time.time_ns()
        latency = max(0.0, (done_ns - w.closed_ns) / 1e9)
        result.update({
            "rig": w.rig,
            "window": {"seq": w.seq, "first_index": w.indices[0], "last_index": w.indices[-1],
                       "frames": len(w.frames), "cameras": sorted(tracks)},
            "smoothed": smoothed,
            "latency_ms": {"estimate": round(seconds * 1e3, 2), "last_frame_to_result": round(latency * 1e3, 2)},
            "published_ns": done_ns,
        })
        publisher.put(json.dumps(result, separators=(",", ":")))
        self.metrics.window_latency.observe(latency)
        self.metrics.window_estimate.observe(seconds)
        self.metrics.windows.labels(w.rig, "estimated").inc()
        with self._lock:
            rig.recent.append(result)
            rig.estimated += 1
            rig.last_logged_index = max(rig.last_logged_index, w.indices[-1])
        if self.rerun is not None and bundle is not None:
            try:
                self._rerun_queue.put_nowait((w.rig, bundle, w.indices[-1], smoothed))
            except queue.Full:  # drawing fell behind: skip this window's drawing, not its estimate
                self.metrics.rerun_skipped.labels(w.rig).inc()
        if feedback and est is not None:
            with self._lock:
                if w.rig in self._feedback_todo:
                    self.metrics.feedback_superseded.labels(w.rig).inc()
                self._feedback_todo[w.rig] = (w, est, tracks, sizes)
                self._feedback_ready.notify()

    def _feedback_loop(self) -> None:
        """Make and publish priors, newest window of each rig first; never blocks estimation."""
        while True:
            with self._lock:
                while not self._feedback_todo and not self._stop.is_set():
                    self._feedback_ready.wait(timeout=0.1)
                if self._stop.is_set():
                    return
                rig = next(iter(self._feedback_todo))
                job = self._feedback_todo.pop(rig)
            try:
                self._feedback(*job)
            except Exception:  # keep the loop alive; this window's priors are lost
                log.exception("feedback priors for %s failed", rig)

    def _feedback(self, w: Window, est, tracks: dict[str, CameraTrack],
                  sizes: dict[str, tuple[int, int]]) -> None:
        """Render and publish priors for the next frames of every camera (§7.1).

        Each prior names the agent run (epoch) whose frame indices it predicts,
        so a restarted agent ignores it; the agent checks it against its own
        evidence before use (``capture.segment``).
        """
        t0 = time.perf_counter()
        with self._lock:
            lag_s = self._rigs[w.rig].feedback_lag_s
        # Frames captured before these priors can arrive need none: skip them.
        period_s = _frame_period_s(w.frames)
        skip = 0 if period_s is None or lag_s is None else int(lag_s / period_s)
        future = self.feedback_pool.submit(predict_feedback, est, tracks, w.indices, sizes,
                                           self.settings.feedback_ahead, skip)
        deadline = time.monotonic() + 60
        while True:  # in slices, so that close() need not wait for it
            try:
                priors = future.result(timeout=0.1)
                break
            except concurrent.futures.TimeoutError:
                if self._stop.is_set() or time.monotonic() > deadline:
                    future.cancel()
                    return
        # The run whose frame indices the window holds (not a run that started since).
        epochs = {cam: m.epoch_ns for fs in w.frames for cam, m in fs.parts.items()}
        with self._lock:
            if self._stop.is_set():
                return
            rig = self._rigs[w.rig]
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
                msg = FeedbackMessage(rig=w.rig, camera=cam, frame_index=index, box=Box(*box),
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
            return {
                "rig": rig.name,
                "cameras": {c: s.to_dict() for c, s in sorted(rig.cameras.items())},
                "windows": {"seq": rig.window_seq, "estimated": rig.estimated, "skipped": rig.skipped,
                            "failed": rig.failed, "dropped": rig.dropped},
                "feedback": {"enabled": self.feedback_pool is not None, "priors_sent": rig.priors_sent},
                "frames": {"late": a.late, "duplicate": a.duplicate, "missing": a.missing,
                           "restarts": rig.restarts, "gaps": rig.buffer.resets},
                "viewpoints": {c: t.state() for c, t in sorted(rig.tracks.items())},
                "latest_seq": None if latest is None else latest["window"]["seq"],
            }

    def latest(self, name: str) -> dict | None:
        with self._lock:
            rig = self._rigs.get(name)
            return None if rig is None or not rig.recent else rig.recent[-1]

    def since(self, name: str, seq: int, limit: int) -> list[dict] | None:
        with self._lock:
            rig = self._rigs.get(name)
            if rig is None:
                return None
            return [r for r in rig.recent if r["window"]["seq"] > seq][:limit]

    def has_rig(self, name: str) -> bool:
        with self._lock:
            return name in self._rigs

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
                    if pub is not None:
                        try:
                            pub.undeclare()
                        except Exception:
                            pass
