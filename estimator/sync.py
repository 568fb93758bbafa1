"""Offline synchronisation of recorded videos from the walk itself.

Cameras that were not triggered together (phones, webcams) start at different
moments and may run at different frame rates; their frames cannot be paired by
index. The walker's gait phase is the same in every view at the same instant
(Izo–Grimson §6: the phase is a property of the walker, not of the view), so
each camera's own phase over its own clock, estimated alone, fixes its offset
to the others to a fraction of a frame, modulo a gait cycle. Whole cycles are
told apart by what is not periodic: the walker's pace drifting (people speed
up and slow down, start and stop), which shows in the phase itself over the
whole overlap (docs/SYNC.md: why the image track cannot add to it).

Choices where nothing published guides us (docs/SYNC.md):

* One camera is the reference (the one with the most frames showing the walker,
  unless given); each other camera's offset is found against it alone, on a
  grid of ``SyncConfig.resolution_s`` over ``±max_offset_s``, refined by a
  parabola through the best grid point and its neighbours.
* A camera's phase may be decoded half a cycle off (left and right legs look
  alike from the front): the half-cycle-shifted match competes with a small
  penalty (``SyncConfig.half_cycle_penalty``).
* The offset is ``ambiguous`` when the best match of another part of the cycle
  (at least a quarter cycle away) is within ``SyncConfig.min_margin`` of the
  best: a walker at a perfectly even pace gives no way to tell whole cycles
  apart, and the result says so rather than guessing silently.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace

import numpy as np

from .appearance import AppearanceModel
from .hmm import posterior, viterbi
from .pipeline import CameraTrack, EstimateConfig, estimate_walk

__all__ = ["CameraClock", "SyncConfig", "SyncResult", "align_tracks", "camera_clock", "index_frames", "index_pairing_cost",
           "sync_offsets", "sync_tracks", "synchronize", "timeline_frames", "timeline_rate", "tracks_on_timeline"]


@dataclass(frozen=True)
class SyncConfig:
    """Options of :func:`synchronize`.

    Parameters
    ----------
    max_offset_s : float
        Largest offset searched, either way (s).
    resolution_s : float
        Step of the search grid (s); the result is refined below it.
    reference : str, optional
        The camera whose clock the offsets are on (default: the one that shows
        the walker longest).
    min_overlap_s : float
        Offsets that leave less shared time than this are not considered.
    half_cycle_penalty : float
        Added to the cost of a match that pairs a camera's phase with the
        reference's opposite phase (a left/right confusion).
    full_cycle_weight : float
        Weight of the match of the phase itself against that of the phase
        modulo half a cycle (:func:`_costs`).
    unexplained : float
        Cost of a frame that the reference did not see at that offset.
    min_margin : float
        Cost margin below which the best offset is reported ``ambiguous``, for
        cameras that see the walker ``margin_span_s`` or longer; a shorter view
        needs ``sqrt(margin_span_s / seconds seen)`` times more (the margin is a
        mean over fewer frames).
    margin_span_s : float
    together_margin : float
        The index pairing's margin (as ``min_margin`` in :func:`sync_tracks`) for
        recordings of equal frame rate and length, which a rig started together
        makes and hand-started cameras hardly ever do: their index pairing
        stands unless the best offsets fit the walk better by this much (mean
        pair cost). Synchronised 3 s walks (CMU motion, random bodies) gave gaps
        up to 0.09 on exact silhouettes and up to 0.37 through a real background
        and the segmenter, but 0.5-1.05 in 4 of 24 walks (two draws) where one
        camera's phase was spoiled; real offsets of equal-length clips gave
        0.65-2.05, and 0.41-0.51 for offsets the walk found wrong anyway (14
        frames of 2.8 s clips), or 0.004-0.07 for whole numbers of half cycles,
        which the walk cannot tell from zero (docs/SYNC.md).
    together_cadence : float
        For such recordings, the largest disagreement of the cameras' cadences
        (fastest over slowest, minus one) at which the walk may still move them.
        Each camera's clock is its own phase track; when two of them run more
        than this apart, at least one is wrong (spoiled silhouettes, a
        left/right confusion) and so is any offset found from it. On 3 s
        composite walks (docs/SYNC.md) every synchronised rig that the walk
        moved had clocks 17-86 % apart, except one; clean silhouettes agree
        within a few percent.
    min_fps : float
        Cameras slower than this are reported ``ambiguous`` whatever the margin:
        a gait cycle of about a second needs some eight frames to be followed.
    hints : dict of str to float, optional
        Rough offsets (s, on the reference's clock) known otherwise (a clap, the
        files' times): a hinted camera's offset is searched within
        ``hint_reach_s`` of its hint only (less than a quarter of a gait cycle
        either way), which settles whole and half cycles when the walk cannot.
    """

    max_offset_s: float = 2.5
    resolution_s: float = 0.002
    reference: str | None = None
    min_overlap_s: float = 2.0
    half_cycle_penalty: float = 0.05
    full_cycle_weight: float = 0.25
    unexplained: float = 0.1
    min_margin: float = 0.02
    together_margin: float = 0.5
    together_cadence: float = 0.1
    margin_span_s: float = 6.0
    min_fps: float = 8.0
    hints: dict[str, float] | None = None
    hint_reach_s: float = 0.2

    def __post_init__(self) -> None:
        if not (self.max_offset_s > 0 and self.resolution_s > 0 and self.min_overlap_s > 0):
            raise ValueError("max_offset_s, resolution_s and min_overlap_s must be positive, got "
                             f"{self.max_offset_s}, {self.resolution_s}, {self.min_overlap_s}")


@dataclass
class CameraClock:
    """One camera's walk on its own clock (:func:`camera_clock`).

    Attributes
    ----------
    times : ndarray of shape (T,)
        Seconds from the camera's first frame.
    phase : ndarray of shape (T,)
        Unwrapped gait phase (cycles, continuous), NaN where the camera did not
        see the walker.
    fps : float
    """

    times: np.ndarray
    phase: np.ndarray
    fps: float

    @property
    def seen(self) -> np.ndarray:
        """Frames with a phase."""
        return np.isfinite(self.phase)


@dataclass
class SyncResult:
    """Per camera, where its clock sits on the reference's (:func:`synchronize`).

    ``offsets_s[c]`` is the reference's time of camera ``c``'s first frame: camera
    ``c``'s frame ``k`` was taken at reference time ``offsets_s[c] + k / fps[c]``.
    """

    reference: str
    offsets_s: dict[str, float]
    fps: dict[str, float]
    uncertainty_s: dict[str, float]
    margin: dict[str, float]
    ambiguous: dict[str, bool]
    notes: list[str] = field(default_factory=list)
    best_cost: float = np.nan  # mean pair cost at these offsets

    def offsets_frames(self) -> dict[str, float]:
        """Each offset in frames of its own camera."""
        return {c: self.offsets_s[c] * self.fps[c] for c in self.offsets_s}

    def to_dict(self) -> dict:
        """JSON-able form (the ``sync`` block of a result, docs/FORMATS.md); None where unknown."""
        def num(x: float, digits: int) -> float | None:
            return round(float(x), digits) if np.isfinite(x) else None

        return {
            "reference": self.reference,
            "cameras": {c: {"offset_s": num(self.offsets_s[c], 5),
                            "offset_frames": num(self.offsets_s[c] * self.fps[c], 3),
                            "fps": num(self.fps[c], 4),
                            "uncertainty_s": num(self.uncertainty_s[c], 5),
                            "margin": num(self.margin[c], 4),
                            "ambiguous": self.ambiguous[c]} for c in self.offsets_s},
            "notes": self.notes,
        }


def camera_clock(track: CameraTrack, model: AppearanceModel, fps: float, *,
                 config: EstimateConfig | None = None,
                 cadences: np.ndarray = np.arange(0.6, 1.41, 0.05)) -> CameraClock:
    """The walker's phase over one camera's own frames.

    The camera is estimated alone (:func:`estimator.pipeline.estimate_walk`); its phase
    evidence is then decoded again by HMMs whose advance per frame matches each of
    ``cadences`` (cycles/s) at the camera's frame rate (:meth:`PhaseHMM.scaled`), and the
    likeliest is kept. The default HMM's prior (1.29 cycles/s at 15 Hz) pulls the path
    faster than most walkers on weak evidence: over a 6 s recording that drift is more
    than a cycle, and every offset found from it would be wrong. The decoded state is
    refined to a continuous phase by the posterior's mean within three states of it, and
    unwrapped along the path.
    """
    config = config or EstimateConfig()
    est = estimate_walk({"c": track}, model, config=config)
    seen = est.cameras["c"].labels >= 0
    hmm = config.hmm
    k = hmm.n_states
    with np.errstate(divide="ignore"):
        log_start = np.log(hmm.startprob_)
        decoded = []
        for cadence in cadences:
            h = hmm.scaled(k * cadence / fps / hmm.mean_advance)
            log_prob, states = viterbi(log_start, np.log(h.transmat_), est.log_emission)
            decoded.append((log_prob, states, h))
    _, states, h = max(decoded, key=lambda d: d[0])
    with np.errstate(divide="ignore"):
        post = posterior(log_start, np.log(h.transmat_), est.log_emission)
    states = states.astype(int)
    steps = np.arange(-3, 4)
    near = post[np.arange(len(states))[:, None], (states[:, None] + steps) % k]
    refined = states + (near * steps).sum(axis=1) / np.maximum(near.sum(axis=1), 1e-12)
    phase = np.unwrap(refined / k, period=1.0)
    phase[~seen] = np.nan
    times = np.arange(len(states)) / fps
    return CameraClock(times, phase, float(fps))


def synchronize(clocks: dict[str, CameraClock], config: SyncConfig | None = None) -> SyncResult:
    """Each camera's offset to the reference camera (module docstring).

    Every pair of cameras is compared over the offset grid; each camera keeps the few best
    parts of the cycle against the reference, and the combination that agrees best over
    all pairs wins (three cameras tell a whole cycle apart better than two). A camera's
    margin is against the best combination that moves it to another part of the cycle.

    Raises
    ------
    ValueError
        Fewer than two cameras, an unknown reference, or a camera without a phase.
    """
    config = config or SyncConfig()
    if len(clocks) < 2:
        raise ValueError(f"synchronisation needs two or more cameras, got {len(clocks)}")
    bare = [c for c, clk in clocks.items() if clk.seen.sum() < 3]
    if bare:
        raise ValueError(f"camera(s) {', '.join(bare)}: the walker is not seen, nothing to synchronise on")
    names = list(clocks)
    ref = config.reference or max(names, key=lambda c: (clocks[c].seen.sum(), -names.index(c)))
    if ref not in clocks:
        raise ValueError(f"reference camera {ref!r} is not among {sorted(clocks)}")
    # Pairs of non-reference cameras can be up to twice the search range apart.
    grid = np.arange(-2 * config.max_offset_s, 2 * config.max_offset_s + config.resolution_s / 2,
                     config.resolution_s)
    curves = {(a, b): _curve(clocks[a], clocks[b], grid, config) for i, a in enumerate(names) for b in names[i + 1:]}
    cadence = _cadence(clocks[ref])
    spacing = 0.25 / cadence
    others = [c for c in names if c != ref]
    hints = config.hints or {}
    unknown = sorted(set(hints) - set(names))
    if unknown:
        raise ValueError(f"hints for unknown camera(s) {', '.join(unknown)} (cameras: {', '.join(names)})")
    if ref in hints and hints[ref] != 0.0:  # hints are on the reference's clock
        hints = {c: h - hints[ref] for c, h in hints.items()}
    candidates = {c: _minima(grid, _pair_cost(curves, ref, c), spacing, config.max_offset_s,
                             around=hints.get(c), reach=config.hint_reach_s) for c in others}
    notes = [f"{c}: shares less than {config.min_overlap_s} s with {ref} at any offset within "
             f"±{config.max_offset_s} s; not synchronised" for c in others if not candidates[c]]
    others = [c for c in others if candidates[c]]
    combos = _combinations([candidates[c] for c in others]) if others else []
    scores = np.array([_agreement(curves, {ref: 0.0, **dict(zip(others, combo))}, grid) for combo in combos])
    offsets = {c: (0.0 if c == ref else np.nan) for c in names}
    margin = {c: (np.inf if c == ref else 0.0) for c in names}
    ambiguous = {c: c != ref for c in names}
    unc = {c: (0.0 if c == ref else np.nan) for c in names}
    if combos:
        best = combos[int(np.argmin(scores))]
        fixed = {ref: 0.0, **dict(zip(others, best))}
        for i, c in enumerate(others):
            moved = [k for k, combo in enumerate(combos) if abs(combo[i] - best[i]) >= spacing]
            margin[c] = float(scores[moved].min() - scores.min()) if moved else np.inf
            seen_s = min(clocks[c].seen.sum() / clocks[c].fps, clocks[ref].seen.sum() / clocks[ref].fps)
            ambiguous[c] = bool(margin[c] < config.min_margin * np.sqrt(max(1.0, config.margin_span_s / seen_s)))
            offsets[c] = _refine(curves, fixed, c, grid)
            unc[c] = _standard_error(clocks[ref], clocks[c], offsets[c], cadence)
            if ambiguous[c]:
                notes.append(f"{c}: another part of the gait cycle fits almost as well (margin {margin[c]:.3f}); "
                             "the walker's pace is too even to tell whole cycles apart")
    for c in names:
        if clocks[c].fps < config.min_fps:
            ambiguous[c] = c != ref or ambiguous[c]
            notes.append(f"{c}: {clocks[c].fps:g} fps is below {config.min_fps:g}: fewer than about eight frames "
                         "per gait cycle, its phase aliases and its offset is not to be trusted")
    return SyncResult(ref, offsets, {c: clk.fps for c, clk in clocks.items()}, unc, margin, ambiguous, notes,
                      best_cost=float(scores.min()) if combos else np.nan)


def _curve(a: CameraClock, b: CameraClock, grid: np.ndarray, config: SyncConfig) -> np.ndarray:
    """Cost of each offset of ``b`` on ``a``'s clock; inf where they share too little time."""
    cost, overlap = _costs(a, b, grid, config)
    return np.where(overlap >= config.min_overlap_s, cost, np.inf)


def _pair_cost(curves: dict, a: str, b: str) -> np.ndarray:
    """The cost curve of ``b``'s offset on ``a``'s clock, whichever way the pair was computed
    (``a`` at +x on ``b``'s clock is ``b`` at -x on ``a``'s; the grid is symmetric)."""
    return curves[(a, b)] if (a, b) in curves else curves[(b, a)][::-1]


def _minima(grid: np.ndarray, cost: np.ndarray, spacing: float, limit: float, k: int = 4, *,
            around: float | None = None, reach: float = 0.0) -> list[float]:
    """Up to ``k`` best offsets within ``±limit`` (within ``reach`` of ``around`` when given),
    at least ``spacing`` apart."""
    inside = np.abs(grid) <= limit + 1e-9 if around is None else np.abs(grid - around) <= reach + 1e-9
    cost = np.where(inside, cost, np.inf)
    out: list[float] = []
    for i in np.argsort(cost, kind="stable"):
        if not np.isfinite(cost[i]) or len(out) == k:
            break
        if all(abs(grid[i] - o) >= spacing for o in out):
            out.append(float(grid[i]))
    return out


def _combinations(lists: list[list[float]], cap: int = 4096) -> list[tuple[float, ...]]:
    """Every choice of one candidate per camera; past ``cap`` choices, each camera's
    alternatives with the others at their best."""
    if np.prod([len(x) for x in lists], dtype=float) > cap:
        firsts = tuple(x[0] for x in lists)
        return [firsts] + [firsts[:i] + (alt,) + firsts[i + 1:] for i, x in enumerate(lists) for alt in x[1:]]
    return list(itertools.product(*lists))


def _agreement(curves: dict, offsets: dict[str, float], grid: np.ndarray) -> float:
    """Mean cost over the pairs that share time at these offsets."""
    values = [_at(grid, curve, offsets[b] - offsets[a]) for (a, b), curve in curves.items()
              if a in offsets and b in offsets]
    values = [v for v in values if np.isfinite(v)]
    return float(np.mean(values)) if values else np.inf


def _at(grid: np.ndarray, curve: np.ndarray, x: float) -> float:
    """The curve at the grid point nearest ``x`` (inf off the grid)."""
    i = int(np.rint((x - grid[0]) / (grid[1] - grid[0])))
    return float(curve[i]) if 0 <= i < len(grid) else np.inf


def _refine(curves: dict, offsets: dict[str, float], cam: str, grid: np.ndarray, reach: int = 10) -> float:
    """``cam``'s offset with the others fixed: the summed cost of its pairs within ``reach``
    grid steps of its candidate, minimised and refined by a parabola through the best
    point and its neighbours."""
    step = grid[1] - grid[0]
    xs = offsets[cam] + step * np.arange(-reach, reach + 1)
    total = np.zeros(len(xs))
    for other, off in offsets.items():
        if other != cam:
            curve = _pair_cost(curves, other, cam)
            vals = np.array([_at(grid, curve, x - off) for x in xs])
            if np.isfinite(vals).all():
                total += vals
    i = int(np.argmin(total))
    best = float(xs[i])
    if 0 < i < len(xs) - 1:
        a, b, c = total[i - 1:i + 2]
        if a - 2 * b + c > 0:
            best += 0.5 * (a - c) / (a - 2 * b + c) * step
    return best


def _cadence(clock: CameraClock) -> float:
    """Cycles per second over the camera's seen frames."""
    seen = clock.seen
    t, p = clock.times[seen], clock.phase[seen]
    return float(max(abs(np.polyfit(t, p, 1)[0]), 0.2)) if len(t) > 2 else 1.0


def _pairs(ref: CameraClock, cam: CameraClock, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference phase at each of ``cam``'s frames for each offset (G, T) and whether defined."""
    when = cam.times[None, :] + grid[:, None]
    seen = ref.seen
    t, p = ref.times[seen], ref.phase[seen]
    at = np.interp(when, t, p)
    # Defined where the reference saw the walker within a frame of that instant.
    gap = np.abs(when - t[np.clip(np.searchsorted(t, when), 0, len(t) - 1)])
    gap = np.minimum(gap, np.abs(when - t[np.clip(np.searchsorted(t, when) - 1, 0, len(t) - 1)]))
    ok = (when >= t[0]) & (when <= t[-1]) & (gap <= 1.01 / ref.fps) & cam.seen[None, :]
    return at, ok


def _costs(ref: CameraClock, cam: CameraClock, grid: np.ndarray, config: SyncConfig
           ) -> tuple[np.ndarray, np.ndarray]:
    """Per offset: the phase disagreement over ``cam``'s frames, and the shared time (s).

    A frame the reference also saw costs ``1 - cos`` of twice the phase difference (blind
    to a left/right confusion, which side views make: their silhouettes half a cycle apart
    look alike) plus ``full_cycle_weight`` times the smaller of ``1 - cos`` and
    ``1 + cos`` + ``half_cycle_penalty`` of the difference itself; a frame the reference
    did not see (outside the overlap) costs ``unexplained``, so that a short overlap that
    happens to agree does not beat a long one that agrees as well.
    """
    at, ok = _pairs(ref, cam, grid)
    d = 2 * np.pi * (np.where(ok, cam.phase[None, :], 0.0) - np.where(ok, at, 0.0))
    full = np.minimum(1 - np.cos(d), 1 + np.cos(d) + config.half_cycle_penalty)
    per_frame = np.where(ok, 1 - np.cos(2 * d) + config.full_cycle_weight * full, config.unexplained)
    n = ok.sum(axis=1)
    cost = np.where(cam.seen[None, :], per_frame, 0.0).sum(axis=1) / max(int(cam.seen.sum()), 1)
    return np.where(n > 0, cost, np.inf), n / cam.fps


def _standard_error(ref: CameraClock, cam: CameraClock, offset: float, cadence: float) -> float:
    """Standard error of ``offset`` (s): the phase residuals' spread in time over the frames'
    count, one effective sample per half second (neighbouring frames' errors are correlated)."""
    at, ok = _pairs(ref, cam, np.array([offset]))
    r = (cam.phase - at[0] + 0.25) % 0.5 - 0.25  # residual within the matched half cycle
    r = r[ok[0]]
    if r.size < 3:
        return np.inf
    n_eff = max(1.0, r.size / max(1.0, 0.5 * cam.fps))
    return float(np.std(r) / cadence / np.sqrt(n_eff))


def timeline_frames(lengths: dict[str, int], sync: SyncResult, *, fps: float | None = None
                    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """Each camera's own frame at each instant of one timeline, and the timeline's times.

    The timeline runs at ``fps`` (default the slowest camera's rate, so that no
    frame is used twice) on the reference's clock, from the earliest camera's
    first frame to the latest's last; each camera of ``lengths`` (its frame
    count) gives its nearest frame within half of its own frame interval, or -1.
    Cameras without an offset are left out. Anything indexed by a camera's own
    frames (silhouettes, a detector's keypoints) goes on the timeline through
    these indices.
    """
    rate = fps or min(sync.fps[c] for c in lengths)
    usable = [c for c in lengths if np.isfinite(sync.offsets_s.get(c, np.nan))]
    if not usable:
        raise ValueError("no camera has an offset")
    start = min(sync.offsets_s[c] for c in usable)
    stop = max(sync.offsets_s[c] + (lengths[c] - 1) / sync.fps[c] for c in usable)
    times = start + np.arange(int(np.floor((stop - start) * rate + 1e-9)) + 1) / rate
    frames = {}
    for name in usable:
        pos = (times - sync.offsets_s[name]) * sync.fps[name]
        k = np.rint(pos).astype(int)
        ok = (k >= 0) & (k < lengths[name]) & (np.abs(pos - k) <= 0.5 + 1e-9)
        frames[name] = np.where(ok, k, -1)
    return frames, times


def align_tracks(tracks: dict[str, CameraTrack], sync: SyncResult, *, fps: float | None = None
                 ) -> tuple[dict[str, CameraTrack], np.ndarray]:
    """The tracks on one timeline (:func:`timeline_frames`): frames paired by time, not by index.

    Returns the aligned tracks and the timeline's times (s, reference clock).
    """
    frames, times = timeline_frames({c: len(t.silhouettes) for c, t in tracks.items()}, sync, fps=fps)
    return tracks_on_timeline(tracks, frames), times


def tracks_on_timeline(tracks: dict[str, CameraTrack], frames: dict[str, np.ndarray]) -> dict[str, CameraTrack]:
    """Each camera of ``frames`` with its own frame ``frames[c][i]`` at frame ``i`` (none where -1)."""
    out = {}
    for name, k in frames.items():
        t = tracks[name]
        sils = [t.silhouettes[j] if j >= 0 else None for j in k]
        boxes = np.where((k >= 0)[:, None], np.asarray(t.boxes, float)[np.maximum(k, 0)], np.nan)
        out[name] = CameraTrack(sils, boxes, t.full_frame, t.image_size)
    return out


def sync_tracks(tracks: dict[str, CameraTrack], fps: dict[str, float], model: AppearanceModel, *,
                config: SyncConfig | None = None, estimate: EstimateConfig | None = None
                ) -> tuple[dict[str, CameraTrack], float, SyncResult, dict[str, np.ndarray]]:
    """Recorded cameras synchronised from the walk (:func:`sync_offsets`) and put on one
    timeline: the tracks, the timeline's rate, the offsets and each camera's own frame at each
    frame of the timeline (:func:`timeline_frames`; what else is numbered by each camera's
    frames, a detector's keypoints, follows them)."""
    result = sync_offsets(tracks, fps, model, config=config, estimate=estimate)
    frames, times = timeline_frames({c: len(t.silhouettes) for c, t in tracks.items()}, result)
    return tracks_on_timeline(tracks, frames), timeline_rate(times, fps), result, frames


def index_frames(lengths: dict[str, int]) -> dict[str, np.ndarray]:
    """Each camera's own frame at each frame of a timeline that pairs the frames by index (as
    :func:`timeline_frames` gives them): frame ``i`` is every camera's ``i``, -1 past a camera's
    last of ``lengths``."""
    n = np.arange(max(lengths.values(), default=0))
    return {c: np.where(n < m, n, -1) for c, m in lengths.items()}


def timeline_rate(times: np.ndarray, fps: dict[str, float]) -> float:
    """The rate of a timeline of :func:`timeline_frames` (the slowest of ``fps`` for a single instant)."""
    return float(1.0 / np.median(np.diff(times))) if len(times) > 1 else min(fps.values())


def sync_offsets(tracks: dict[str, CameraTrack], fps: dict[str, float], model: AppearanceModel, *,
                 config: SyncConfig | None = None, estimate: EstimateConfig | None = None) -> SyncResult:
    """Each recorded camera's offset, from the walk (:func:`camera_clock`, :func:`synchronize`).

    With equal frame rates, when pairing the frames by index fits the walk about as well
    as the best offsets found (within ``config.min_margin``; ``config.together_margin`` when
    the recordings are also equally long, as a rig started together makes them), the index
    pairing stands: cameras that were started together stay as they were; the result says so.
    Equally long recordings whose cameras' cadences disagree by more than
    ``config.together_cadence`` keep the index pairing too: their clocks cannot be trusted.
    """
    config = config or SyncConfig()
    clocks = {}
    for c, t in tracks.items():
        try:
            clocks[c] = camera_clock(t, model, fps[c], config=estimate)
        except ValueError:  # no silhouette in this camera at all
            pass
    seen = {c: clk for c, clk in clocks.items() if clk.seen.sum() >= 3}
    if len(seen) >= 2:
        result = synchronize(seen, replace(config, reference=config.reference if config.reference in seen else None))
    else:
        first = next(iter(tracks))
        result = SyncResult(first, {first: 0.0}, {first: fps[first]}, {first: 0.0}, {first: np.inf}, {first: False},
                            ["fewer than two cameras show the walker: nothing to synchronise on"])
    blind = [c for c in tracks if c not in result.offsets_s]
    if blind:
        result = replace(result, offsets_s={**result.offsets_s, **{c: np.nan for c in blind}},
                         fps={**result.fps, **{c: fps[c] for c in blind}},
                         uncertainty_s={**result.uncertainty_s, **{c: np.nan for c in blind}},
                         margin={**result.margin, **{c: 0.0 for c in blind}},
                         ambiguous={**result.ambiguous, **{c: True for c in blind}})
    lost = [c for c, o in result.offsets_s.items() if not np.isfinite(o)]
    if lost:  # too little walk to tell: taken as started with the reference, and said
        result = replace(result, offsets_s={c: (0.0 if c in lost else o) for c, o in result.offsets_s.items()},
                         notes=result.notes + [f"{', '.join(lost)}: taken as started with {result.reference} "
                                               "(the walk could not synchronise it)"])
    rates = {round(f, 3) for f in fps.values()}
    if len(rates) == 1 and any(abs(o) * result.fps[c] >= 0.5 for c, o in result.offsets_s.items()):
        index_cost = index_pairing_cost(clocks, config)
        together = len({len(t.silhouettes) for t in tracks.values()}) == 1
        margin = config.together_margin if together else config.min_margin
        cadences = sorted(_cadence(clk) for clk in seen.values())
        spread = cadences[-1] / cadences[0] - 1 if len(cadences) > 1 else 0.0
        if together and spread > config.together_cadence:
            result = _by_index(result, tracks, index_cost, [
                f"the videos have the same frame rate and length and the cameras' walks disagree on the "
                f"cadence ({cadences[0]:.2f}-{cadences[-1]:.2f} cycles/s, {spread:.0%} apart, more than "
                f"{config.together_cadence:.0%}): the walk cannot move cameras started together; paired by "
                "index"])
        elif index_cost - result.best_cost < margin:
            why = "the videos have the same frame rate and length, " if together else ""
            result = _by_index(result, tracks, index_cost, [
                f"{why}pairing frames by index fits the walk within {margin} of the best offsets: kept "
                "(the cameras look started together)"])
    return result


def _by_index(result: SyncResult, tracks: dict[str, CameraTrack], index_cost: float, notes: list[str]
              ) -> SyncResult:
    """``result`` with every offset zero (frames paired by index), saying why."""
    return SyncResult(result.reference, {c: 0.0 for c in tracks}, result.fps, {c: np.nan for c in tracks},
                      result.margin, {c: False for c in tracks}, result.notes + notes, best_cost=index_cost)


def index_pairing_cost(clocks: dict[str, CameraClock], config: SyncConfig) -> float:
    """The mean pair cost of :func:`synchronize` with every offset zero (frames paired by index)."""
    names = list(clocks)
    zero = np.zeros(1)
    values = [float(_costs(clocks[a], clocks[b], zero, config)[0][0])
              for i, a in enumerate(names) for b in names[i + 1:]]
    return float(np.mean(values))
