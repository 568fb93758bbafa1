"""The capture agent: frames -> silhouettes -> ``posecal/<rig>/<camera>/silhouette``.

One agent per camera. It opens the source and learns the background: from
frames of a recording sampled over its first seconds (re-read; the scene
need not be empty, segmentation starts at frame 0), else from the first
``warmup_frames`` frames (live cameras; recorded sources are read as fast as
possible meanwhile, then replayed in real time). It segments every frame and
publishes one :class:`~capture.wire.SilhouetteMessage` per frame, empty or
not. It subscribes to its ``feedback`` key and hands valid priors to the
segmenter (paper §7.1).

Each run has an epoch (its start time in ns) and numbers its messages from 0,
so receivers can tell a restart from a gap. Zenoh re-establishes links by
itself (connect retries are configured in :mod:`capture.zconfig`); the agent
keeps producing and logs when subscribers appear and vanish. SIGINT/SIGTERM
end the loop after the current frame; the session closes cleanly.
"""

from __future__ import annotations

import collections
import logging
import signal
import re
import threading
import time
import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
import zenoh
from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict

from .live import LiveSegmenter
from .receiver import ValidatingSubscriber
from .scene import iou
from .segment import PriorStats, Segmentation, Segmenter, SegmentSettings, box_iou, sample_indices
from .sources import Frame, FrameSource, SourceError, make_source, paced, read_plate
from .wire import (N_JOINTS, FeedbackMessage, Quality, SilhouetteMessage, encode, feedback_key,
                   keypoints_for_frame, silhouette_key)

__all__ = ["AgentSettings", "AgentStats", "CaptureView", "main"]

log = logging.getLogger(__name__)


class AgentSettings(BaseSettings):
    """Everything an agent needs besides the Zenoh config (env: ``POSECAL_CAPTURE_*``)."""

    model_config = SettingsConfigDict(env_prefix="POSECAL_CAPTURE_", env_nested_delimiter="__",
                                      frozen=True)

    rig: str = Field("rig0", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    camera: str = Field("c0", pattern=r"^[A-Za-z0-9_.-]{1,64}$")
    source: str = Field("device:0", description="source spec, see capture.sources")
    fps: float | None = Field(None, gt=0, description="replay rate of recorded sources "
                                                      "(default: the source's fps, else 30)")
    max_frames: int | None = Field(None, ge=1, description="stop after this many frames "
                                                          "(warm-up included)")
    stale_ms: float = Field(250.0, gt=0, description="drop live frames older than this")
    stats_interval_s: float = Field(5.0, gt=0, description="how often to log fps/drops/latency")
    png_compression: int = Field(1, ge=0, le=9)
    opencv_threads: int | None = Field(None, ge=1, description="cap OpenCV's threads (1 when "
                                       "several agents share a host); default: OpenCV's choice")
    score_truth: bool = Field(False, description="score each silhouette against the source's "
                              "ground truth when it has one (synthetic; benchmarks), after "
                              "publishing")
    quality_every: int = Field(30, ge=1, description="messages between quality figures on the "
                               "wire (the first message carries them too)")
    rerun: str | None = Field(None, description="Rerun sink for the camera view, save:PATH | "
                              "serve[:PORT] | connect[:URL]; opened by `posecal capture`, which "
                              "hands main() the view (off by default)")
    rerun_every: int = Field(10, ge=1, description="segmented frames between views logged to "
                             "Rerun (raw frame, background, silhouette), so viewing never slows "
                             "capture")
    background_image: str | None = Field(None, description="an image of the empty scene (a file of the "
                                         "source's frame size): the background, where the walker stays in "
                                         "the same place in the view for most of the time it is learned "
                                         "over (a treadmill, a walk straight at the camera)")
    segment: SegmentSettings = SegmentSettings()


@dataclass
class AgentStats:
    """Counters of one agent run; ``latency_ms`` is capture-to-publish of recent messages."""

    epoch_ns: int
    frames: int = 0  # frames read from the source, warm-up included
    warmup: int = 0
    published: int = 0
    unheard: int = 0  # published while no subscriber matched (Zenoh discards them)
    dropped_gap: int = 0  # frame indices the source skipped
    dropped_stale: int = 0  # live frames too old to be worth segmenting
    errors: int = 0  # publish failures
    priors: int = 0  # feedback priors received and valid for this run
    priors_other_epoch: int = 0  # ... meant for another run of this camera (ignored)
    priors_ahead: int = 0  # frames whose own prior had arrived before their capture time
    priors_behind: int = 0  # frames, once priors flow, whose prior had not (late or missing)
    priors_late: int = 0  # priors that arrived after their frame had been segmented
    segmented_index: int = -1  # the last frame index segmented
    prior_use: PriorStats = field(default_factory=PriorStats)  # the segmenter's
    iou_sum: float = 0.0  # against the source's ground truth, when it has one (synthetic)
    iou_frames: int = 0
    streaming_s: float = 0.0  # wall time from the end of warm-up to the end of the run
    cpu_s: float = 0.0  # process CPU time over the same span (all threads)
    latency_ms: collections.deque = field(default_factory=lambda: collections.deque(maxlen=2000))
    segmented: int = 0  # frames segmented (after the background was known)
    with_walker: int = 0  # ... in which a walker was found
    candidates: int = 0  # person-sized candidates seen in the last frame
    walker_moves: int = 0  # the track moved to another person by a look back (capture.choose.LiveChoice)
    joined_cut: int = 0  # silhouettes cut back to the walker where someone joined them (capture.merges.LiveUnmerge)
    walker_held: bool = False  # a look back found the walker held in place with no background image (warned)
    areas: collections.deque = field(default_factory=lambda: collections.deque(maxlen=500))
    stability: collections.deque = field(default_factory=lambda: collections.deque(maxlen=500))
    _last_box: tuple | None = None

    def observe(self, seg: Segmentation) -> None:
        """Count one silhouette for the quality figures (walker fraction, area, stability)."""
        self.segmented += 1
        self.candidates = seg.n_candidates
        if seg.box.empty:
            self._last_box = None
            return
        self.with_walker += 1
        self.areas.append(seg.area)
        box = (seg.box.x, seg.box.y, seg.box.w, seg.box.h)
        if self._last_box is not None:
            self.stability.append(box_iou(self._last_box, box))
        self._last_box = box

    def quality(self) -> Quality:
        """Walker fraction, median silhouette area (px) and median box IoU between
        consecutive silhouettes (1 = steady; a flickering or jumping mask scores low;
        None before two consecutive silhouettes), as sent on the wire."""
        return Quality(walker_fraction=self.with_walker / self.segmented if self.segmented else 0.0,
                       area_median=float(np.median(self.areas)) if self.areas else 0.0,
                       stability=float(np.median(self.stability)) if self.stability else None)

    @property
    def fps(self) -> float:
        """Silhouettes sent per second after warm-up."""
        return self.sent / self.streaming_s if self.streaming_s > 0 else 0.0

    @property
    def sent(self) -> int:
        """Silhouettes put on the wire, heard or not."""
        return self.published + self.unheard

    @property
    def dropped(self) -> int:
        return self.dropped_gap + self.dropped_stale + self.errors

    @property
    def mean_iou(self) -> float:
        """Mean silhouette IoU against the source's ground truth (nan without one)."""
        return self.iou_sum / self.iou_frames if self.iou_frames else float("nan")

    @property
    def prior_ahead_fraction(self) -> float:
        """Of the frames since the first prior, the fraction whose prior came in time."""
        n = self.priors_ahead + self.priors_behind
        return self.priors_ahead / n if n else float("nan")

    def latency_percentiles(self) -> tuple[float, float]:
        """(p50, p99) of recent capture-to-publish latencies in ms (nan if none)."""
        if not self.latency_ms:
            return float("nan"), float("nan")
        p50, p99 = np.percentile(np.fromiter(self.latency_ms, float), [50, 99])
        return float(p50), float(p99)


class _StopOnSignals:
    """Set ``stop`` on SIGINT/SIGTERM while active (only possible in the main thread)."""

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self._previous: dict[int, object] = {}

    def __enter__(self) -> None:
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._previous[sig] = signal.signal(sig, self._handle)

    def _handle(self, signum: int, _frame: object) -> None:
        log.info("%s received, stopping", signal.Signals(signum).name)
        self.stop.set()

    def __exit__(self, *exc: object) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


class _Matching:
    """Tracks whether any subscriber matches the publisher, and logs changes."""

    def __init__(self, publisher: zenoh.Publisher, key: str) -> None:
        self.matching = publisher.matching_status.matching
        self._key = key
        self._listener = publisher.declare_matching_listener(zenoh.handlers.Callback(self._on))

    def _on(self, status: zenoh.MatchingStatus) -> None:
        self.matching = status.matching
        if status.matching:
            log.info("subscriber(s) present on %s", self._key)
        else:
            log.warning("no subscriber on %s; frames are discarded until one returns", self._key)


class _PriorClock:
    """When each frame's prior arrived, to tell whether it came before the frame (§7.1)."""

    def __init__(self) -> None:
        self._arrivals: dict[int, int] = {}  # frame index -> wall-clock ns of its first prior
        self._lock = threading.Lock()  # priors arrive on Zenoh's thread

    def arrived(self, index: int, now_ns: int) -> None:
        with self._lock:
            self._arrivals.setdefault(index, now_ns)

    def check(self, frame: Frame, stats: AgentStats) -> None:
        """Count ``frame`` as ahead (its prior came before its capture time) or behind."""
        with self._lock:
            arrived = self._arrivals.pop(frame.index, None)
            for old in [k for k in self._arrivals if k < frame.index]:
                del self._arrivals[old]
        if arrived is not None and arrived <= frame.timestamp_ns:
            stats.priors_ahead += 1
            return
        stats.priors_behind += 1
        log.debug("frame %d: its prior %s", frame.index, "not yet here" if arrived is None
                  else f"came {(arrived - frame.timestamp_ns) / 1e6:.0f} ms late")


def _bootstrap(source: FrameSource, segmenter: Segmenter) -> bool:
    """Bootstrap the background from frames re-read from a recording (False if it cannot
    be re-read, or the old warm-up is asked for): segmentation then starts at frame 0."""
    s = segmenter.settings
    n = None if source.live or s.background != "bootstrap" else source.frame_count()
    if not n:
        return False
    indices = sample_indices(n, source.fps, s)
    images = source.sample(indices)
    if not images:
        return False
    segmenter.bootstrap(images)
    log.info("background bootstrapped from %d frames sampled over frames 0-%d", len(images), indices[-1])
    return True


def _warm_up(frames: Iterator[Frame], segmenter: Segmenter, stats: AgentStats,
             stop: threading.Event) -> None:
    """Learn the background from the first frames (paper §7: 100 empty frames)."""
    while segmenter.warming_up and not stop.is_set():
        frame = next(frames, None)
        if frame is None:
            return
        segmenter.apply(frame.image, frame.index)
        stats.frames += 1
        stats.warmup += 1
    if segmenter.warming_up and not stop.is_set():
        log.warning("the source ended during warm-up (%d frames); nothing to segment", stats.warmup)
    else:
        log.info("background learned from %d frames", stats.warmup)


def _log_stats(stats: AgentStats, sent_before: int, seconds: float, what: str) -> None:
    p50, p99 = stats.latency_percentiles()
    log.info("%s: %.1f fps, published %d (unheard %d), dropped %d (gap %d, stale %d, errors %d), "
             "capture-to-publish p50 %.2f ms p99 %.2f ms, priors %d (used %d, rejected %d, "
             "stale %d, late %d, in time for %d/%d frames)%s", what,
             (stats.sent - sent_before) / max(seconds, 1e-9), stats.published,
             stats.unheard, stats.dropped, stats.dropped_gap, stats.dropped_stale, stats.errors,
             p50, p99, stats.priors, stats.prior_use.used, stats.prior_use.rejected,
             stats.prior_use.stale, stats.priors_late, stats.priors_ahead,
             stats.priors_ahead + stats.priors_behind,
             f", IoU vs ground truth {stats.mean_iou:.3f} over {stats.iou_frames} frames"
             if stats.iou_frames else "")
    q = stats.quality()
    log.info("%s quality: walker in %.0f%% of %d frames, median area %.0f px, stability %s, "
             "candidates %d, track moved to the walker %d times, %d frames cut back where someone joined",
             what, 100 * q.walker_fraction, stats.segmented, q.area_median,
             "-" if q.stability is None else f"{q.stability:.2f}", stats.candidates, stats.walker_moves,
             stats.joined_cut)


class CaptureView(Protocol):
    """Where the agent shows what it sees: :class:`service.rerun_log.RerunLog` for
    ``posecal capture --rerun`` (the capture package itself imports no Rerun)."""

    def log_capture(self, camera: str, index: int, frame: np.ndarray,
                    background: np.ndarray | None, silhouette: np.ndarray) -> None:
        """One frame (BGR), the background model (BGR, None if unknown) and the
        full-frame silhouette (uint8 0/255) at frame ``index``."""


def _show(view: CaptureView, camera: str, frame: Frame, seg: Segmentation,
          segmenter: Segmenter) -> bool:
    """Log one frame to ``view``; False (logged once) if viewing failed: capture goes on."""
    try:
        # A copy: the view may hold the pixels after this returns, and sources may reuse buffers.
        view.log_capture(camera, frame.index, frame.image.copy(), segmenter.background_image(),
                         seg.full_mask())
        return True
    except Exception:
        log.exception("logging the camera view failed; viewing is off for this run")
        return False


def main(conf: zenoh.Config, settings: AgentSettings, *, source: FrameSource | None = None,
         stop: threading.Event | None = None, view: CaptureView | None = None,
         keypoints: Mapping[int, np.ndarray] | None = None) -> AgentStats:
    """Run one agent until the source ends, ``max_frames``, ``stop`` or a signal.

    ``source`` overrides ``settings.source`` (benchmarks pass in-memory ones).
    ``keypoints``: a pose detector's 13 joints (13, 2) per frame index, sent with
    that frame's silhouette (``SilhouetteMessage.keypoints``; ``posecal capture
    --keypoints`` reads them from a detector's files).
    ``view`` receives every ``settings.rerun_every``-th segmented frame, after it
    was published (the caller opens and closes it, as it does the Zenoh config).
    Raises :class:`~capture.sources.SourceError` if the source cannot be opened.
    """
    stop = stop or threading.Event()
    if keypoints is not None and (bad := [k for k, v in keypoints.items() if np.shape(v) != (N_JOINTS, 2)]):
        raise ValueError(f"keypoints must be ({N_JOINTS}, 2) per frame (posecal's joints), frames {bad[:3]} "
                         f"are {np.shape(keypoints[bad[0]])}")
    if settings.opencv_threads is not None:
        cv2.setNumThreads(settings.opencv_threads)
    stats = AgentStats(epoch_ns=time.time_ns())
    # Spread the rig's background updates over the frames: a phase per camera
    # (its number, c0, c1, ..., else a hash of its name).
    number = re.search(r"(\d+)$", settings.camera)
    phase = (int(number.group(1)) if number else zlib.crc32(settings.camera.encode())) % settings.segment.update_every
    source_name = settings.source if source is None else type(source).__name__
    source = source if source is not None else make_source(settings.source)
    try:
        plate = None if settings.background_image is None else read_plate(settings.background_image, source.size)
    except SourceError:
        source.close()
        raise
    segmenter = Segmenter(settings.segment.model_copy(update={"update_phase": phase}), plate=plate)
    key = silhouette_key(settings.rig, settings.camera)
    sync = "index" if source.hardware_sync else "time"

    clock = _PriorClock()
    stats.prior_use = segmenter.prior_stats

    def on_prior(prior: FeedbackMessage) -> None:
        if prior.epoch_ns and prior.epoch_ns != stats.epoch_ns:
            stats.priors_other_epoch += 1
            return
        now = time.time_ns()
        if prior.frame_index <= stats.segmented_index:
            stats.priors_late += 1
        if segmenter.set_prior(prior, now_ns=now):
            stats.priors += 1
            clock.arrived(prior.frame_index, now)

    with _StopOnSignals(stop), source, zenoh.open(conf) as session:
        publisher = session.declare_publisher(
            key, congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE, express=True)
        matching = _Matching(publisher, key)
        feedback = ValidatingSubscriber(session, feedback_key(settings.rig, settings.camera),
                                        FeedbackMessage, on_message=on_prior)
        log.info("agent %s/%s epoch %d: source %s (live=%s, sync by %s) -> %s",
                 settings.rig, settings.camera, stats.epoch_ns, source_name, source.live, sync, key)
        frames = iter(source)
        if not _bootstrap(source, segmenter):
            _warm_up(frames, segmenter, stats, stop)
        if not source.live:
            frames = paced(frames, settings.fps or source.fps or 30.0)
        last_index, seq = None, 0
        live = LiveSegmenter(segmenter)
        started = last_log = time.monotonic()
        cpu_started = time.process_time()
        sent_at_log = 0
        for frame in frames:
            if stop.is_set() or (settings.max_frames and stats.frames >= settings.max_frames):
                break
            stats.frames += 1
            if last_index is not None and frame.index > last_index + 1:
                stats.dropped_gap += frame.index - last_index - 1
            last_index = frame.index
            if source.live and time.time_ns() - frame.timestamp_ns > settings.stale_ms * 1e6:
                stats.dropped_stale += 1
                continue
            if stats.priors:  # the feedback loop runs: was this frame's prior in time?
                clock.check(frame, stats)
            seg = live.apply(frame.image, frame.index)
            stats.joined_cut = live.cut
            stats.segmented_index = frame.index
            stats.observe(seg)
            msg = SilhouetteMessage(
                rig=settings.rig, camera=settings.camera, frame_index=frame.index,
                capture_ns=frame.timestamp_ns, box=seg.box, image_size=seg.image_size,
                epoch_ns=stats.epoch_ns, seq=seq,
                mask=seg.mask, sync=sync, publish_ns=time.time_ns(),
                n_candidates=int(seg.n_candidates),
                quality=stats.quality() if seq % settings.quality_every == 0 else None,
                keypoints=None if keypoints is None else keypoints_for_frame(keypoints.get(frame.index),
                                                                             seg.image_size),
                track_id=live.track_id, track_from=live.track_from)
            seq += 1
            try:
                publisher.put(encode(msg, png_compression=settings.png_compression))
            except zenoh.ZError as exc:
                stats.errors += 1
                log.error("publish failed on %s: %s", key, exc)
                continue
            if matching.matching:
                stats.published += 1
            else:
                stats.unheard += 1
            stats.latency_ms.append((time.time_ns() - frame.timestamp_ns) / 1e6)
            if live.learn():  # the deferred background update and a look back, off the latency path
                stats.walker_moves += 1
                log.info("%s/%s frame %d: %s", settings.rig, settings.camera, frame.index, live.note)
            if live.held and plate is None and not stats.walker_held:
                stats.walker_held = True
                log.warning("%s/%s frame %d: %s", settings.rig, settings.camera, frame.index, live.held)
            if view is not None and (stats.segmented - 1) % settings.rerun_every == 0:
                view = view if _show(view, settings.camera, frame, seg, segmenter) else None
            if settings.score_truth and frame.mask is not None and frame.mask.any():
                stats.iou_sum += iou(seg.full_mask(), frame.mask)
                stats.iou_frames += 1
            now = time.monotonic()
            if now - last_log >= settings.stats_interval_s:
                _log_stats(stats, sent_at_log, now - last_log, "last interval")
                last_log, sent_at_log = now, stats.sent
        feedback.close()
        publisher.undeclare()
        stats.streaming_s = time.monotonic() - started
        stats.cpu_s = time.process_time() - cpu_started
        _log_stats(stats, 0, stats.streaming_s,
                   f"agent {settings.rig}/{settings.camera} stopped after {stats.frames} frames")
    return stats
