"""A recording as sliding windows, cut where the walker changes heading.

The cameras can be taken as fixed relative to the walker only while the
walker keeps one heading: a turn changes every camera's viewpoint (Izo–Grimson
§3 fits a viewpoint per window of frames). The live service estimates short
windows and smooths each camera's viewpoint across them
(:class:`ViewpointTrack`). A recording is treated the same way
(:func:`segment_walk`): windows of ``length`` frames every ``hop``, each
estimated on its own; a :class:`ViewpointTrack` per camera finds the windows
where a viewpoint changed (``confirm`` consecutive windows agreeing on a new
viewpoint more than ``threshold_deg`` away); the windows between two changes
form a segment, estimated again as one window so that it has all of its
frames' evidence. A walker who keeps one heading gives one segment, the
whole recording, exactly as one window would.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from .appearance import AppearanceModel
from .joints import N_JOINTS
from .matchcache import MatchCache
from .mnbp import MNBPConfig, measure_postures
from .pipeline import CameraTrack, EstimateConfig, WalkEstimate, estimate_walk, track_length
from .rig import RigConfig, attach_rig, calibrate_rig
from .viewpoint import azimuth_difference_deg, circular_mean_deg

__all__ = ["Segment", "SegmentedWalk", "ViewpointTrack", "earlier_azimuths", "own_azimuth", "segment_walk",
           "window_starts", "window_tracks"]


def _view_distance(a: tuple[float, float], b: tuple[float, float]) -> float:
    return max(abs(float(azimuth_difference_deg(a[0], b[0]))), abs(a[1] - b[1]))


class ViewpointTrack:
    """A camera's viewpoint smoothed across windows, with change detection.

    Windows within ``threshold_deg`` of the smoothed value refine it (running
    mean over up to ``memory`` windows). A window farther away is held as an
    outlier; ``confirm`` consecutive outliers that agree with each other mean
    the viewpoint changed (the camera moved, or the walker turned): the
    estimate restarts from them and a change is recorded, at the index of the
    first of them. A lone outlier never moves the estimate. A value resting on
    fewer than ``settle`` windows restarts so without a change recorded, and
    as soon as more consecutive windows agree with each other against it than
    it rests on: a live rig's first window can be its cameras' start-up
    (frames of one camera before the other was heard from, a track on someone
    else before the agent's first look back), and the windows after it
    outvoting it is a bad start, not a move.
    """

    def __init__(self, *, threshold_deg: float, confirm: int, memory: int = 10, settle: int = 0) -> None:
        self.threshold, self.confirm, self.memory, self.settle = threshold_deg, confirm, memory, settle
        self.value: tuple[float, float] | None = None
        self.n = 0
        self.streak = 0  # the last windows in a row that agree with the value
        self.pending: list[tuple[float, float, int]] = []
        self.changes: list[dict[str, Any]] = []
        self.outliers = 0

    def update(self, az: float | None, el: float | None, index: int) -> dict[str, Any]:
        """Add one window's viewpoint (None/NaN: the camera saw nothing; no change)."""
        if az is not None and el is not None and np.isfinite(az) and np.isfinite(el):
            self._update(float(az) % 360.0, float(el), index)
        return self.state()

    def _update(self, az: float, el: float, index: int) -> None:
        if self.value is None:
            self.value, self.n, self.streak = (az, el), 1, 1
            return
        if _view_distance((az, el), self.value) <= self.threshold:
            self.pending.clear()
            self.n = min(self.n + 1, self.memory)
            self.streak += 1
            a = 1.0 / self.n
            self.value = ((self.value[0] + a * float(azimuth_difference_deg(az, self.value[0]))) % 360.0,
                          self.value[1] + a * (el - self.value[1]))
            return
        self.outliers += 1
        self.streak = 0
        self.pending.append((az, el, index))
        outvoted = self.n < self.settle and len(self.pending) > self.n  # a young value, more windows against it
        if len(self.pending) < self.confirm and not outvoted:
            return
        ref = self.pending[-1][:2]
        if all(_view_distance(p[:2], ref) <= self.threshold for p in self.pending):
            new = (circular_mean_deg(np.array([p[0] for p in self.pending])),
                   float(np.mean([p[1] for p in self.pending])))
            if self.n >= self.settle:
                self.changes.append({"frame_index": self.pending[0][2],
                                     "from": [round(v, 2) for v in self.value],
                                     "to": [round(v, 2) for v in new]})
            self.value, self.n = new, len(self.pending)
            self.streak = self.n
            self.pending.clear()
        else:
            self.pending = self.pending[-(self.confirm - 1):] if self.confirm > 1 else []

    def state(self) -> dict[str, Any]:
        v = self.value
        return {"azimuth_deg": None if v is None else round(v[0], 3),
                "elevation_deg": None if v is None else round(v[1], 3),
                "windows": self.n, "pending_outliers": len(self.pending),
                "outliers": self.outliers, "changes": list(self.changes)}


def earlier_azimuths(tracks: dict[str, ViewpointTrack], least: int) -> dict[str, float] | None:
    """Each camera's smoothed azimuth where its last ``least`` windows in a row agreed with it (0: none),
    the ``earlier`` of :func:`estimator.pipeline.decode_walk` for the next window of a fixed rig. A
    camera with an outlier among its last windows may be changing (the walker turned): on walks up and
    down a walkway, stale values met again after the second turn once held a camera to the heading in
    between (``bench/eval_live_replay.py --synthetic 20 --turn 180``)."""
    if least < 1:
        return None
    return {cam: t.value[0] for cam, t in tracks.items() if t.value is not None and t.streak >= least} or None


def own_azimuth(azimuth: float | None, flip: str | None) -> float | None:
    """The azimuth a window found for a camera by itself: the mirror across the ahead/behind fold of
    a viewpoint held on its earlier side (``flip`` ``"earlier"``). The smoothing is fed this, so that
    it never feeds on its own hold and a smoothed value on the wrong side is still outvoted."""
    return (180.0 - azimuth) % 360.0 if azimuth is not None and flip == "earlier" else azimuth


def window_starts(n_frames: int, length: int, hop: int) -> np.ndarray:
    """First frames of the windows over ``n_frames``: every ``hop``, the last one ending at the end.

    A recording of at most ``length`` frames is one window starting at 0.
    """
    if length < 1 or hop < 1:
        raise ValueError(f"window length and hop must be positive, got {length} and {hop}")
    if n_frames <= length:
        return np.zeros(1, int)
    starts = np.arange(0, n_frames - length + 1, hop)
    if starts[-1] + length < n_frames:
        starts = np.append(starts, n_frames - length)
    return starts


@dataclass
class Segment:
    """A stretch of the recording with one heading, estimated as one window.

    Attributes
    ----------
    start, stop : int
        Frames ``[start, stop)`` the estimate covers (whole windows).
    first, last : int
        The frames this segment reports (segments report disjoint stretches:
        where two overlap, each frame goes to the nearer window centre).
    estimate : WalkEstimate or None
        None where nothing could be estimated (``error`` says why).
    windows : int
        Sliding windows in the segment.
    error : str
    """

    start: int
    stop: int
    first: int
    last: int
    estimate: WalkEstimate | None
    windows: int
    error: str = ""


@dataclass
class SegmentedWalk:
    """A recording's segments, in order, and each window's viewpoints.

    Attributes
    ----------
    segments : list of Segment
    windows : list of dict
        Per sliding window: ``first_index``, ``last_index``, ``segment`` and
        per camera ``azimuth_deg`` / ``elevation_deg`` (None where the window
        had no estimate for it), or ``error``.
    """

    segments: list[Segment]
    windows: list[dict]

    @property
    def main(self) -> int:
        """Index of the estimated segment that reports the most frames."""
        done = [k for k, s in enumerate(self.segments) if s.estimate is not None]
        return max(done, key=lambda k: self.segments[k].last - self.segments[k].first)

    def to_result(self) -> dict:
        """The DESIGN.md result with ``segments`` and ``windows``.

        ``cameras`` are the viewpoints of the longest segment (of the whole
        recording when the walker kept one heading); each frame carries the
        ``segment`` that reports it, whose ``cameras`` give its viewpoints.
        """
        per = [None if seg.estimate is None else seg.estimate.to_result(first_index=seg.start)
               for seg in self.segments]
        frames: list[dict] = []
        segments = []
        for k, (seg, res) in enumerate(zip(self.segments, per)):
            out = {"first_index": seg.first, "last_index": seg.last, "windows": seg.windows}
            if res is None:
                out["error"] = seg.error
                frames += [{"index": t, "phase": None, "joints3d": None, "joints2d": {}, "observed_phase": {},
                            "segment": k} for t in range(seg.first, seg.last + 1)]
            else:
                out.update(cameras=res["cameras"], hmm=res["hmm"], notes=res["notes"],
                           **{k: res[k] for k in ("rig", "body") if k in res})
                frames += [dict(f, segment=k) for f in res["frames"][seg.first - seg.start:seg.last + 1 - seg.start]]
            segments.append(out)
        main = self.segments[self.main]
        result = dict(per[self.main])
        result.update(frames=frames, segments=segments, windows=self.windows)
        if len(self.segments) > 1:
            result["notes"] = result["notes"] + [
                f"the viewpoints changed during the recording: {len(self.segments)} segments; cameras are "
                f"those of the longest (frames {main.first}-{main.last}), see segments"]
        return result


def window_tracks(tracks: dict[str, CameraTrack], a: int, b: int) -> dict[str, CameraTrack]:
    """Frames ``[a, b)`` of every camera's track."""
    return {n: t.take(slice(a, b)) for n, t in tracks.items()}


def _estimate(tracks, a, b, model, config, cache=None) -> tuple[WalkEstimate | None, str]:
    try:
        return estimate_walk(window_tracks(tracks, a, b), model, config=config, cache=cache), ""
    except ValueError as exc:
        return None, str(exc)


def segment_walk(
    tracks: dict[str, CameraTrack],
    model: AppearanceModel,
    *,
    length: int = 20,
    hop: int = 10,
    threshold_deg: float = 30.0,
    confirm: int = 3,
    config: EstimateConfig | None = None,
    posture: MNBPConfig | None = None,
    rig: RigConfig | None = None,
    keypoints: dict[str, np.ndarray] | None = None,
    progress: Callable[[float], None] | None = None,
) -> SegmentedWalk:
    """Estimate a recording window by window, one segment per heading (module docstring).

    Parameters
    ----------
    tracks : dict of str to CameraTrack
        The whole recording; every track has the same number of frames.
    model : AppearanceModel
    length, hop : int
        Frames per window and between window starts.
    threshold_deg, confirm : float, int
        A viewpoint change: ``confirm`` consecutive windows agreeing on a
        viewpoint more than ``threshold_deg`` from the current one.
    config : EstimateConfig, optional
    posture : MNBPConfig, optional
        Measure each segment's 2D postures by mNBP (:func:`estimator.mnbp.measure_postures`,
        once per frame); None keeps the model's placement.
    rig : RigConfig, optional
        Calibrate each segment's rig and the person's posture from them
        (:func:`estimator.rig.calibrate_rig`; the viewpoints' rig without
        ``posture``); None: no rig.
    keypoints : dict of str to ndarray of shape (n_frames, 13, 2), optional
        A detector's joints per camera over the whole recording (full-frame
        pixels, NaN where missed): each segment's rig is calibrated on them
        instead of on the postures (:func:`estimator.rig.calibrate_rig`'s
        ``keypoints``; with ``RigConfig.for_keypoints()``); a camera without
        them has none.
    progress : callable, optional
        Called with the fraction done (windows, then segments).

    Raises
    ------
    ValueError
        No cameras, tracks of different lengths, bad ``length``/``hop``, or
        nothing estimable anywhere (the first window's reason).
    """
    n = track_length(tracks)
    starts = window_starts(n, length, hop)
    stops = np.minimum(starts + length, n)
    progress = progress or (lambda f: None)
    views = {name: ViewpointTrack(threshold_deg=threshold_deg, confirm=confirm) for name in tracks}
    windows, cuts, estimates, errors = [], set(), [], []
    cache = MatchCache(max_entries=4 * length * len(tracks))  # overlapping windows match each frame once
    for k, (a, b) in enumerate(zip(starts, stops)):
        est, err = _estimate(tracks, a, b, model, config, cache)
        estimates.append(est)
        errors.append(err)
        w: dict[str, Any] = {"first_index": int(a), "last_index": int(b) - 1}
        if est is None:
            w["error"] = err
        else:
            w["cameras"] = {}
            for name, c in est.cameras.items():
                vp = c.viewpoint.to_dict()
                w["cameras"][name] = {key: vp[key] for key in ("azimuth_deg", "elevation_deg")}
                before = len(views[name].changes)
                views[name].update(c.viewpoint.azimuth_deg, c.viewpoint.elevation_deg, k)
                cuts.update(c["frame_index"] for c in views[name].changes[before:])
        windows.append(w)
        progress(0.7 * (k + 1) / len(starts))
    if all(errors):
        raise ValueError(errors[0])

    bounds = [0, *sorted(cuts), len(starts)]
    centres = (starts + stops - 1) / 2.0
    segments = []
    for s, (i, j) in enumerate(zip(bounds[:-1], bounds[1:])):
        # Frames from the midpoint with the previous segment's last window centre to the next one's.
        first = 0 if i == 0 else int(np.floor((centres[i - 1] + centres[i]) / 2)) + 1
        last = n - 1 if j == len(starts) else int(np.floor((centres[j - 1] + centres[j]) / 2))
        a, b = int(starts[i]), int(stops[j - 1])
        # A segment of one window is that window's estimate; a longer one is estimated whole.
        est, err = (estimates[i], errors[i]) if j - i == 1 else _estimate(tracks, a, b, model, config, cache)
        if est is not None and posture is not None:
            est = measure_postures(est, posture)
        if est is not None and rig is not None:
            kp = None if keypoints is None else np.stack([
                keypoints[c][a:b] if c in keypoints else np.full((b - a, N_JOINTS, 2), np.nan) for c in est.cameras])
            est = attach_rig(est, calibrate_rig(est, rig, keypoints=kp))
        segments.append(Segment(a, b, first, last, est, j - i, err))
        for w in windows[i:j]:
            w["segment"] = s
        progress(0.7 + 0.3 * (s + 1) / (len(bounds) - 1))
    if all(seg.estimate is None for seg in segments):
        raise ValueError(segments[0].error)
    return SegmentedWalk(segments, windows)
