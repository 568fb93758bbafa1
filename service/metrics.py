"""Prometheus metrics of one service instance (its own registry, so apps don't collide).

Frames in, drops by reason, windows by outcome, latency histograms (window
end-to-end, estimation, jobs), jobs by state (read from the store at scrape
time), the receiver's reject counters, and the rigs and replicas of this one
(gauges, at scrape time). Every label value is bounded: a
rig's series go when the rig is forgotten (:meth:`Metrics.forget_rig`), and
reasons are fixed words.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator

from prometheus_client import CollectorRegistry, Counter, Histogram, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily
from prometheus_client.registry import Collector

from capture.receiver import REJECT_CODES

__all__ = ["DROP_REASONS", "Metrics", "WINDOW_OUTCOMES"]

DROP_REASONS = ("late", "duplicate", "index_ahead")  # posecal_frames_dropped_total{reason}
WINDOW_OUTCOMES = ("estimated", "skipped", "failed", "dropped", "revised")

_LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.075, 0.1, 0.15, 0.2, 0.3, 0.5, 1.0, 2.0, 5.0)
_JOB_BUCKETS = (0.25, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 30.0, 60.0, 300.0)


class _Callback(Collector):
    """Metrics computed at scrape time from a callable returning metric families."""

    def __init__(self, fn: Callable[[], Iterator]) -> None:
        self._fn = fn

    def collect(self) -> Iterator:
        yield from self._fn()


class Metrics:
    """All metrics of the service; ``render()`` is the ``/metrics`` body."""

    def __init__(self) -> None:
        r = self.registry = CollectorRegistry()
        self.frames_in = Counter("posecal_frames_in", "silhouette messages accepted",
                                 ["rig", "camera"], registry=r)
        self.frames_dropped = Counter("posecal_frames_dropped", "silhouette messages dropped "
                                      "(late, duplicate, index_ahead: further ahead of the rig "
                                      "than max_index_ahead)", ["rig", "reason"], registry=r)
        self.live_refused = Counter("posecal_live_refused", "silhouettes refused before touching "
                                    "any rig: a new rig beyond max_rigs (rig_limit) or a new camera "
                                    "beyond max_cameras (camera_limit)", ["reason"], registry=r)
        self.rigs_forgotten = Counter("posecal_rigs_forgotten", "rigs forgotten: silent for "
                                      "rig_expiry_s, or replaced by a new rig at max_rigs", registry=r)
        self.rigs_handed_over = Counter("posecal_rigs_handed_over", "rigs dropped because another "
                                        "replica now estimates them (a replica joined)", registry=r)
        self.frames_not_owned = Counter("posecal_frames_not_owned", "silhouettes skipped before "
                                        "decoding: their rig is estimated by another replica", registry=r)
        self.frames_warmed = Counter("posecal_frames_warmed", "frame sets registered and matched "
                                     "before their window closed (warm_every)", ["outcome"], registry=r)
        self.frames_missing = Counter("posecal_frames_missing", "camera frames absent when a "
                                      "synchronized frame set was closed", ["rig"], registry=r)
        self.windows = Counter("posecal_windows", "sliding windows by outcome "
                               "(estimated, skipped, failed, dropped, revised)", ["rig", "outcome"], registry=r)
        self.window_latency = Histogram("posecal_window_latency_seconds", "arrival of a window's "
                                        "last frame to its published estimate",
                                        buckets=_LATENCY_BUCKETS, registry=r)
        self.window_estimate = Histogram("posecal_window_estimate_seconds", "estimate_walk time "
                                         "of one window in a worker", buckets=_LATENCY_BUCKETS, registry=r)
        self.feedback_priors = Counter("posecal_feedback_priors", "priors published to the "
                                       "segmenters (§7.1)", ["rig"], registry=r)
        self.feedback_superseded = Counter("posecal_feedback_superseded", "windows whose priors "
                                           "were not made because a newer window came first",
                                           ["rig"], registry=r)
        self.feedback_seconds = Histogram("posecal_feedback_seconds", "rendering and publishing "
                                          "one window's priors", registry=r)
        self.rig_seconds = Histogram("posecal_live_rig_seconds", "measuring one live window's postures "
                                     "(and recalibrating the rig, every live_rig_every windows)",
                                     buckets=(0.1, 0.25, 0.5, 1, 2, 4, 8, 16, 32), registry=r)
        self.rerun_skipped = Counter("posecal_rerun_windows_skipped", "live windows not drawn in "
                                     "Rerun because drawing fell behind (estimates unaffected)",
                                     ["rig"], registry=r)
        self.jobs_submitted = Counter("posecal_jobs_submitted", "jobs accepted", registry=r)
        self.jobs_finished = Counter("posecal_jobs_finished", "jobs that ended, by final state",
                                     ["state"], registry=r)
        self.job_duration = Histogram("posecal_job_duration_seconds", "claim to end of a job",
                                      buckets=_JOB_BUCKETS, registry=r)
        self.uploads_rejected = Counter("posecal_uploads_rejected", "uploads answered with a 4xx",
                                        ["status"], registry=r)

    def watch_jobs(self, counts: Callable[[], dict[str, int]]) -> None:
        """Export ``posecal_jobs{state}`` from the store at scrape time."""
        def families():
            g = GaugeMetricFamily("posecal_jobs", "jobs in the store by state", labels=["state"])
            for state, n in counts().items():
                g.add_metric([state], n)
            yield g
        self.registry.register(_Callback(families))

    def watch_receiver(self, stats: Callable[[], object]) -> None:
        """Export the Zenoh receiver's counters (rejected, by reason too; lost, restarts, overflow)."""
        def families():
            s = stats()
            if s is None:
                return
            c = CounterMetricFamily("posecal_receiver_rejected_by_reason", "rejected silhouette "
                                    "messages by reason (the wire's: envelope, header, field, image, "
                                    "key; the receiver's: epoch_future, capture_future; internal)",
                                    labels=["reason"])
            for code in REJECT_CODES:
                c.add_metric([code], s.codes.get(code, 0))
            yield c
            for name, doc, value in (
                ("posecal_receiver_rejected", "malformed silhouette messages", s.rejected),
                ("posecal_receiver_lost", "sequence gaps within an agent epoch", s.lost),
                ("posecal_receiver_restarts", "agent restarts (new epochs)", s.restarts),
                ("posecal_receiver_overflow", "messages dropped by a full queue", s.overflow),
                ("posecal_receiver_stale", "messages from an older epoch", s.stale),
                ("posecal_receiver_readopted", "older epochs taken back after the newer one "
                 "fell silent", s.readopted),
            ):
                c = CounterMetricFamily(name, doc)
                c.add_metric([], value)
                yield c
        self.registry.register(_Callback(families))

    def watch_live(self, counts: Callable[[], tuple[int, int]]) -> None:
        """Export ``posecal_live_rigs`` (rigs this replica estimates) and ``posecal_replicas``
        (alive replicas it sees, itself included) from ``counts()`` at scrape time."""
        def families():
            rigs, replicas = counts()
            for name, doc, value in (("posecal_live_rigs", "live rigs this replica estimates", rigs),
                                     ("posecal_replicas", "alive replicas on the Zenoh network, this "
                                      "one included (1 with replicas off)", replicas)):
                g = GaugeMetricFamily(name, doc)
                g.add_metric([], value)
                yield g
        self.registry.register(_Callback(families))

    def forget_rig(self, rig: str, cameras: list[str], *, handed_over: bool = False) -> None:
        """Remove every series labelled with ``rig`` (the rig was forgotten, or ``handed_over``
        to another replica)."""
        for cam in cameras:
            self.frames_in.remove(rig, cam)
        for reason in DROP_REASONS:
            self.frames_dropped.remove(rig, reason)
        for outcome in WINDOW_OUTCOMES:
            self.windows.remove(rig, outcome)
        for counter in (self.frames_missing, self.feedback_priors, self.feedback_superseded,
                        self.rerun_skipped):
            counter.remove(rig)
        (self.rigs_handed_over if handed_over else self.rigs_forgotten).inc()

    def forget_camera(self, rig: str, camera: str) -> None:
        """Remove the series of one forgotten camera of a rig."""
        self.frames_in.remove(rig, camera)

    def render(self) -> bytes:
        return generate_latest(self.registry)
