"""CPU work of the service: upload intake, batch jobs and window estimation.

Everything heavy runs in worker processes (:func:`make_pool`) that load the
appearance model once (:func:`init_worker`). The event loop only awaits
futures. Two entry points run in the pool:

- :func:`run_job`: read the staged input (sequence folder or videos), build the
  camera tracks, estimate them window by window with one segment per heading
  (:func:`~estimator.windows.segment_walk`), write the result to the job store,
  writing progress as it goes;
- :func:`estimate_window`: one live window, its cameras split over :class:`PinnedPools`
  (:func:`observe_part`, :func:`refine_part` in the workers);
- :func:`predict_feedback`: priors for the frames after a live window (§7.1).

Both can return a :class:`StageBundle`: the plain arrays of every stage that
:mod:`service.rerun_log` draws (inputs, registration, matched cluster means,
viewpoint clouds, phase observations, HMM path, joints).

:func:`stage_upload` (:mod:`service.intake`, re-exported here) runs in the API's
thread pool when a job is submitted: it unpacks and validates the upload so a bad
one is answered with a 4xx at once.
"""

from __future__ import annotations

import collections
import concurrent.futures
import concurrent.futures.process
import itertools
import logging
import math
import multiprocessing
import os
import shutil
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from estimator.appearance import AppearanceModel, load_model
from estimator.matchcache import MatchCache
from estimator.mnbp import MNBPConfig
from estimator.pipeline import (CameraObservation, CameraTrack, PhaseRefinement, WalkEstimate, crop_to_box,
                                decode_walk, estimable_frames, extrapolate_states,
                                observe_cameras, pad_tracks, prime_cache, refine_cameras, tracks_from_sequence)
from estimator.rig import Rig, RigAccumulator, RigConfig
from estimator.sequence import Sequence, read_sequence, write_sequence
from estimator.sync import index_frames, sync_tracks
from estimator.viewpoint import Viewpoint
from estimator.windows import SegmentedWalk, segment_walk, window_tracks

from .intake import UploadError, list_videos, stage_upload
from .keypoints_io import keypoints_on_timeline, read_keypoints
from .jobs import JobGone, JobStore

__all__ = [
    "PinnedPools",
    "StageBundle",
    "UploadError",
    "WorkerPool",
    "estimate_window",
    "make_pinned_pools",
    "predict_feedback",
    "init_worker",
    "make_pool",
    "run_job",
    "stage_upload",
]

log = logging.getLogger(__name__)

_MAX_CLOUD = 1500  # viewpoint-cloud points kept per camera for drawing


# ---------------------------------------------------------------------------- the pool

_model: AppearanceModel | None = None
_stores: dict[str, JobStore] = {}
_renderer = None  # estimator.render.Renderer, made on first use (feedback priors)
# Live windows overlap: each silhouette is registered and matched once per worker process
# (estimator.matchcache; 16 cameras x 4 windows of 20 frames).
_match_cache = MatchCache(max_entries=1280)


def make_pool(n: int, model_path: Path | None, *, renderer: bool = False, nice: int = 0) -> WorkerPool:
    """A process pool whose workers hold the model (unless ``model_path`` is None) and a
    renderer for feedback priors (if asked); started (spawn), warmed up, and replaced if
    a worker dies. ``nice`` lowers the workers' scheduling priority (work that must not
    slow the others down, as the live rig's postures).

    BLAS is kept to one thread per worker: the eq. 8 product is small, and
    OpenBLAS threads spinning against each other on a shared 2-core host made
    it ~6x slower.
    """
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    initargs = (None if model_path is None else str(model_path), renderer, nice, os.getpid())

    def spawn() -> tuple[concurrent.futures.ProcessPoolExecutor, list[concurrent.futures.Future]]:
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=n, mp_context=multiprocessing.get_context("spawn"),
            initializer=init_worker, initargs=initargs)
        return pool, [pool.submit(_ping) for _ in range(n)]  # n calls at once: n workers forked here

    def start() -> concurrent.futures.ProcessPoolExecutor:
        # Forked from one long-lived thread (a worker's parent-death signal follows the
        # thread that forked it, see init_worker); warmed up in the caller's.
        pool, pings = _SPAWNER.submit(spawn).result()
        for f in pings:
            f.result()
        return pool

    return WorkerPool(start)


# Every pool's processes are started by this thread, which lives as long as the service:
# Linux sends a worker its parent-death signal when the *thread* that forked it ends.
_SPAWNER = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix="pool-spawner")


class WorkerPool(concurrent.futures.Executor):
    """A process pool that starts a new one when a worker process dies.

    A worker killed (out of memory, a crash in native code) breaks a
    ``ProcessPoolExecutor`` for good: every later call would fail. Here the
    calls that were running fail (their window or job is counted as failed),
    and the next call starts a fresh pool (``restarts`` counts them).
    """

    def __init__(self, start: Callable[[], concurrent.futures.ProcessPoolExecutor]) -> None:
        self._start = start
        self._pool = start()
        self._lock = threading.Lock()
        self.restarts = 0

    def submit(self, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        with self._lock:
            try:
                return self._pool.submit(fn, *args, **kwargs)
            except concurrent.futures.process.BrokenProcessPool:
                log.warning("a worker process died; starting a new pool")
                _terminate(self._pool)
                self._pool = self._start()
                self.restarts += 1
                return self._pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._pool.shutdown(wait=wait, cancel_futures=cancel_futures)

    def terminate(self) -> None:
        """Stop now: queued calls are cancelled, running workers terminated."""
        _terminate(self._pool)

    @property
    def pids(self) -> list[int]:
        """The current worker processes (for operations and tests)."""
        return [p.pid for p in getattr(self._pool, "_processes", {}).values()]


def _terminate(pool: concurrent.futures.ProcessPoolExecutor) -> None:
    processes = list(getattr(pool, "_processes", {}).values())  # no public API to terminate
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    for p in processes:
        p.join(timeout=5)


def init_worker(model_path: str | None, renderer: bool = False, nice: int = 0,
                parent_pid: int | None = None) -> None:
    """Pool initializer: die with the service (``parent_pid``), load the model once per
    process (if given; and open the renderer)."""
    global _model
    import cv2

    if parent_pid is not None:
        _die_with_parent(parent_pid)

    cv2.setNumThreads(1)
    if nice:
        os.nice(nice)
    if model_path is not None:
        _model = load_model(model_path)
    if renderer:
        _get_renderer()


def _ping() -> int:
    return os.getpid()


_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_WATCH_PARENT_S = 0.5


def _die_with_parent(parent_pid: int) -> None:
    """End this worker when the service process ``parent_pid`` dies, even by SIGKILL.

    Left alone, a worker of a killed service lives on (~700 MB with the model)
    and finishes its job after the next service has re-queued it. On Linux the
    kernel sends SIGKILL on the parent's death (``prctl(PR_SET_PDEATHSIG)``; the
    pools' processes are started from one long-lived thread, see ``_SPAWNER``);
    everywhere, a daemon thread checks every 0.5 s that the parent is still the
    parent (an orphan is adopted by another process) and exits if not.
    """
    import signal
    import sys

    if sys.platform.startswith("linux"):
        try:
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) != 0:
                log.warning("prctl(PR_SET_PDEATHSIG) failed (errno %d); the watchdog remains",
                            ctypes.get_errno())
        except (OSError, AttributeError):
            log.warning("prctl(PR_SET_PDEATHSIG) is not available; the watchdog remains")
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)

    def watch() -> None:
        while True:
            time.sleep(_WATCH_PARENT_S)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="parent-watchdog", daemon=True).start()


def _get_model() -> AppearanceModel:
    if _model is None:
        raise RuntimeError("worker not initialised (init_worker)")
    return _model


def _get_renderer():
    """This worker's renderer (pyrender, EGL), made on first use."""
    global _renderer
    if _renderer is None:
        from estimator.prior import PriorConfig
        from estimator.render import Renderer

        _renderer = Renderer(PriorConfig().body)
    return _renderer


def _store(url: str) -> JobStore:
    if url not in _stores:  # the service has migrated the schema before starting workers
        _stores[url] = JobStore(url, migrate=False)
    return _stores[url]


# ------------------------------------------------------------------------ stage bundle


@dataclass
class StageBundle:
    """Plain arrays of every stage of one estimate, for drawing (no estimator types)."""

    indices: list[int]  # frame index of each of the T frames
    image_size: dict[str, tuple[int, int]]
    crops: dict[str, list[np.ndarray | None]]
    boxes: dict[str, np.ndarray]  # (T, 4)
    registered: dict[str, list[np.ndarray | None]]  # canvas uint8 0/255, None where no input
    labels: dict[str, np.ndarray]  # (T,)
    observations: dict[str, np.ndarray]  # (T,)
    joints2d: dict[str, np.ndarray]  # (T, 13, 2)
    viewpoints: dict[str, dict[str, Any]]  # azimuth_deg, elevation_deg, covariance (2, 2), spread_deg
    clouds: dict[str, np.ndarray]  # (N, 2) member (azimuth, elevation) of the matched clusters
    means: dict[int, np.ndarray]  # matched cluster means, uint8 0..255
    phase: np.ndarray  # (T,)
    states: np.ndarray  # (T,)
    joints3d: np.ndarray  # (T, 13, 3)
    extra: dict[str, Any] = field(default_factory=dict)


def make_bundle(tracks: dict[str, CameraTrack], est: WalkEstimate, model: AppearanceModel | None,
                indices: list[int], image_size: dict[str, tuple[int, int]], *,
                from_frame: int = 0, register: bool = True, rng: int = 0,
                clouds: dict[str, np.ndarray] | None = None) -> StageBundle:
    """Collect what :mod:`service.rerun_log` draws; frames before ``from_frame`` (position
    in the window) are left out of the per-frame images (already drawn).

    With ``register`` False the registered silhouettes and cluster means are left
    empty, for :func:`register_stage` to fill later (off the live latency path).
    ``clouds`` are the cameras' viewpoint clouds if drawn already
    (:func:`viewpoint_clouds`, where the model is); otherwise drawn from ``model``.
    """
    if clouds is None:
        clouds = viewpoint_clouds(model, {name: est.cameras[name].labels for name in tracks}, rng=rng)
    vps = {}
    for name, c in est.cameras.items():
        vp = c.viewpoint
        vps[name] = {"azimuth_deg": float(vp.azimuth_deg), "elevation_deg": float(vp.elevation_deg),
                     "covariance": np.asarray(vp.covariance, float), "spread_deg": float(vp.spread_deg)}
    bundle = StageBundle(
        indices=list(indices), image_size=dict(image_size),
        crops={n: [s if k >= from_frame else None for k, s in enumerate(t.silhouettes)] for n, t in tracks.items()},
        boxes={n: t.boxes for n, t in tracks.items()},
        registered={n: [None] * len(t.silhouettes) for n, t in tracks.items()},
        labels={n: c.labels for n, c in est.cameras.items()},
        observations={n: c.observations for n, c in est.cameras.items()},
        joints2d={n: c.joints2d for n, c in est.cameras.items()},
        viewpoints=vps, clouds=clouds, means={},
        phase=est.phase, states=est.states, joints3d=est.joints3d,
        extra={"from_frame": from_frame, **_rig_extra(est)})
    return register_stage(bundle, model) if register else bundle


def viewpoint_clouds(model: AppearanceModel, labels: dict[str, np.ndarray], *, rng: int = 0
                     ) -> dict[str, np.ndarray]:
    """Per camera, the (azimuth, elevation) of the members of its frames' matched clusters
    (at most ``_MAX_CLOUD``, drawn with ``rng``): the cloud Rerun shows around the viewpoint."""
    gen = np.random.default_rng(rng)
    offsets = model.member_offsets
    clouds = {}
    for name, lab in labels.items():
        matched = lab[lab >= 0]
        if matched.size:
            idx = np.concatenate([np.arange(offsets[k], offsets[k + 1]) for k in matched])
            if idx.size > _MAX_CLOUD:
                idx = gen.choice(idx, _MAX_CLOUD, replace=False)
            clouds[name] = np.stack([model.member_azimuth_deg[idx], model.member_elevation_deg[idx]], -1)
        else:
            clouds[name] = np.zeros((0, 2))
    return clouds


def _rig_extra(est: WalkEstimate) -> dict[str, Any]:
    """The person's posture and the pinhole rig, as plain arrays, when the estimate has them."""
    rig = est.rig
    out: dict[str, Any] = {}
    if rig is not None and rig.joints3d is not None:
        out["person"] = np.asarray(rig.joints3d, float)
    arrays = rig_arrays(rig)
    if arrays is not None:
        out["rig"] = arrays
    return out


def rig_arrays(rig: Rig | None) -> dict[str, Any] | None:
    """A pinhole rig's cameras as plain arrays for Rerun (``RerunLogger.log_rig``); None without one."""
    if rig is None or rig.centres_m is None:
        return None
    return {"cameras": list(rig.cameras), "reference": rig.reference or rig.cameras[0],
            "rotations": np.asarray(rig.rotations, float), "centres_m": np.asarray(rig.centres_m, float),
            "focal_px": np.asarray(rig.focal_px, float), "walker_m": np.asarray(rig.walker_m, float),
            "image_sizes": np.full((len(rig.cameras), 2), np.nan) if rig.image_sizes is None
            else np.asarray(rig.image_sizes, float)}


def register_stage(bundle: StageBundle, model: AppearanceModel | None = None) -> StageBundle:
    """Fill the bundle's registered silhouettes and matched cluster means (in a worker)."""
    model = model or _get_model()
    first = int(bundle.extra.get("from_frame", 0))
    used: set[int] = set()
    for name, crops in bundle.crops.items():
        todo = [k for k in range(first, len(crops)) if crops[k] is not None]
        if not todo:
            continue
        reg, _ = model.register([crops[k] for k in todo])
        labels = bundle.labels[name]
        for k, r in zip(todo, reg):
            bundle.registered[name][k] = (r * 255).astype(np.uint8)
            if labels[k] >= 0:
                used.add(int(labels[k]))
    bundle.means = {k: (model.means[k] * 255).astype(np.uint8) for k in sorted(used)}
    return bundle


def json_safe(value: Any) -> Any:
    """The result with NaN/inf (e.g. the viewpoint of a camera without silhouettes) as None:
    strict JSON for REST and Zenoh."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        if all(type(v) is float for v in value):  # a row of numbers (joints): the common leaf
            return list(value) if all(map(math.isfinite, value)) else [v if math.isfinite(v) else None for v in value]
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        return json_safe(value.item())
    return value


# ---------------------------------------------------------------------------- live windows


class PinnedPools(concurrent.futures.Executor):
    """Worker processes addressed one by one, each a :class:`WorkerPool` of one process.

    A live window's cameras are split over them (:func:`estimate_window`), each
    camera to the same process window after window: there its silhouettes of
    the window before are in the match cache (live windows overlap by half),
    and the window's second stage finds the first stage's registered
    silhouettes where they were made. :meth:`submit` takes turns, for work
    that may run anywhere.
    """

    def __init__(self, pools: list[WorkerPool]) -> None:
        if not pools:
            raise ValueError("no pools")
        self.pools = pools
        self._turn = itertools.count()

    def __len__(self) -> int:
        return len(self.pools)

    def submit(self, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        return self.submit_to(next(self._turn), fn, *args, **kwargs)

    def submit_to(self, k: int, fn, /, *args, **kwargs) -> concurrent.futures.Future:
        """Run ``fn`` in process ``k`` (modulo their number)."""
        return self.pools[k % len(self.pools)].submit(fn, *args, **kwargs)

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        for pool in self.pools:
            pool.shutdown(wait=wait, cancel_futures=cancel_futures)

    def terminate(self) -> None:
        for pool in self.pools:
            pool.terminate()

    @property
    def restarts(self) -> int:
        return sum(pool.restarts for pool in self.pools)

    @property
    def pids(self) -> list[int]:
        return [pid for pool in self.pools for pid in pool.pids]


def make_pinned_pools(n: int, model_path: Path | None) -> PinnedPools:
    """``n`` processes holding the model, started and warmed up side by side."""
    with concurrent.futures.ThreadPoolExecutor(max_workers=n) as starter:
        return PinnedPools(list(starter.map(lambda _: make_pool(1, model_path), range(n))))


# A live window's cameras as observed by this process, until its refine (estimate_window);
# a window whose refine never comes (its decoding failed) is pushed out by later ones.
_observed: collections.OrderedDict[str, dict[str, CameraObservation]] = collections.OrderedDict()
_STALE_OBSERVED = 4  # kept beyond the windows in flight
# Names of the live windows in flight, unique in the service process (a rig forgotten and heard
# again counts its windows from 1 again).
_window_ids = itertools.count()


def observe_part(key: str, tracks: dict[str, CameraTrack], *, clouds: bool = False, in_flight: int = 2,
                 earlier: dict[str, float] | None = None
                 ) -> tuple[dict[str, CameraObservation], dict[str, np.ndarray] | None]:
    """A live window's first stage for some of its cameras, in a worker: their light
    observations (:func:`~estimator.pipeline.observe_cameras`), and their viewpoint clouds
    for Rerun if asked; the registered silhouettes stay here under ``key`` (with those of
    at most ``in_flight`` other windows, and a few whose refine never came)."""
    model = _get_model()
    observed = observe_cameras(tracks, model, cache=_match_cache, earlier=earlier)
    _observed[key] = observed
    while len(_observed) > in_flight + _STALE_OBSERVED:
        _observed.popitem(last=False)
    drawn = viewpoint_clouds(model, {n: o.estimate.labels for n, o in observed.items()}) if clouds else None
    return {n: o.light() for n, o in observed.items()}, drawn


def refine_part(key: str, states: np.ndarray, sides: dict[str, bool]) -> dict[str, PhaseRefinement]:
    """A live window's second stage for the cameras :func:`observe_part` kept under ``key``, in a
    worker (:func:`~estimator.pipeline.refine_cameras`)."""
    observed = _observed.pop(key, None)
    if observed is None:
        raise RuntimeError(f"window {key}: its observed cameras are gone (the worker was restarted, or more "
                           "windows were in flight than it keeps)")
    return refine_cameras(observed, states, _get_model(), sides=sides, cache=_match_cache)


def camera_shares(names: list[str], rig: str, n: int) -> dict[int, list[str]]:
    """Which of ``n`` processes observes which of a rig's cameras: dealt in turn, from a
    place fixed by the rig's name (so that several small rigs do not all start on one)."""
    first = zlib.crc32(rig.encode())
    shares: dict[int, list[str]] = {}
    for i, name in enumerate(names):
        shares.setdefault((first + i) % n, []).append(name)
    return shares


@dataclass
class WindowBefore:
    """What a rig's newest estimated window said, for a look at the next one's frames before it
    closes (:func:`warm_window`): its sequence number, frame indices, decoded states and
    cameras' viewpoints."""

    seq: int
    indices: np.ndarray
    states: np.ndarray
    viewpoints: dict[str, Viewpoint]

    @classmethod
    def of(cls, seq: int, indices: list[int], est: WalkEstimate) -> WindowBefore:
        return cls(seq, np.asarray(indices), est.states, {c: e.viewpoint for c, e in est.cameras.items()})

    def guess(self, indices: list[int] | np.ndarray, n_states: int) -> dict[str, Any]:
        """:func:`~estimator.pipeline.prime_cache`'s guess for frames ``indices`` of the next
        window: this one's viewpoints, its phase carried on (``extrapolate_states``)."""
        return {"viewpoints": self.viewpoints,
                "states": extrapolate_states(self.indices, self.states, n_states, np.asarray(indices))}


def warm_part(tracks: dict[str, CameraTrack], indices: list[int], before: WindowBefore | None) -> int:
    """Frames ``indices`` of a live window not yet closed, for some of its cameras, taken through
    what the window will ask of the match cache, at the window ``before``'s viewpoints and phase
    carried on (:func:`~estimator.pipeline.prime_cache`), in a worker: the frames looked at."""
    model = _get_model()
    guess = {} if before is None else before.guess(indices, model.exemplars().n_phases)
    return prime_cache(tracks, model, _match_cache, **guess)


def warm_window(pools: PinnedPools, rig: str, tracks: dict[str, CameraTrack], indices: list[int],
                before: WindowBefore | None = None) -> concurrent.futures.Future:
    """Send frames ``indices`` of a live window not yet closed to the processes that will
    estimate its cameras (:func:`camera_shares`, as :func:`estimate_window` deals them;
    ``tracks`` in sorted camera order), with what the rig's window ``before`` said: a future
    done when all are (its result: the frames looked at). The window's estimate is the same
    with or without: only its wait is shorter."""
    futures = [pools.submit_to(k, warm_part, {n: tracks[n] for n in share}, indices, before)
               for k, share in camera_shares(list(tracks), rig, len(pools)).items()]
    return _all_of(futures)


def _all_of(futures: list[concurrent.futures.Future]) -> concurrent.futures.Future:
    """One future for several (their results summed): done when the last is, with the first
    error (a cancelled one's too). The callbacks run in the pools' threads, several at once."""
    done: concurrent.futures.Future = concurrent.futures.Future()
    left = [len(futures)]
    lock = threading.Lock()

    def collect(_: concurrent.futures.Future) -> None:
        with lock:
            left[0] -= 1
            if left[0]:
                return
        if any(f.cancelled() for f in futures):
            done.set_exception(concurrent.futures.CancelledError())
        elif errors := [f.exception() for f in futures if f.exception() is not None]:
            done.set_exception(errors[0])
        else:
            done.set_result(sum(f.result() for f in futures))

    if not futures:
        done.set_result(0)
    for f in futures:
        f.add_done_callback(collect)
    return done


def match_cache_stats() -> dict[str, int]:
    """This worker's match-cache hits and misses so far, of silhouettes and of derived results
    (for tests and benchmarks)."""
    c = _match_cache
    return {"hits": c.hits, "misses": c.misses, "derived_hits": c.derived_hits, "derived_misses": c.derived_misses}


def estimate_window(pools: PinnedPools, rig: str, tracks: dict[str, CameraTrack], indices: list[int],
                    image_size: dict[str, tuple[int, int]], *, bundle_from: int | None = None,
                    in_flight: int = 2, timeout_s: float = 60.0, earlier: dict[str, float] | None = None
                    ) -> tuple[dict, StageBundle | None, float, WalkEstimate]:
    """Estimate one live window with its cameras split over ``pools``: ``(result, bundle, seconds,
    estimate)``. Runs in the calling thread, the work in the pools.

    Cameras are independent until the HMM (§6): each process observes its
    share (``observe_part``), the HMM joins them here
    (:func:`~estimator.pipeline.decode_walk`), each process votes its cameras'
    viewpoints again at the decoded phases (``refine_part``), and the HMM
    decodes again; the estimate is :func:`~estimator.pipeline.estimate_walk`'s.
    A camera's process is fixed by its place among ``tracks`` (sorted names)
    and the ``rig``'s name; ``in_flight`` is how many windows the caller may
    estimate at once; ``earlier`` holds the cameras' azimuths found over the rig's
    earlier windows (:func:`~estimator.pipeline.decode_walk`). The bundle is None
    unless ``bundle_from`` is given.
    ValueError: nothing estimable.
    """
    t0 = time.perf_counter()
    estimable_frames(tracks)
    names = list(tracks)
    key = f"{rig}/{next(_window_ids)}"
    shares = camera_shares(names, rig, len(pools))
    observing = {k: pools.submit_to(k, observe_part, key, {n: tracks[n] for n in share},
                                    clouds=bundle_from is not None, in_flight=in_flight, earlier=earlier)
                 for k, share in shares.items()}
    light: dict[str, CameraObservation] = {}
    clouds: dict[str, np.ndarray] = {}
    for future in observing.values():
        part, drawn = future.result(timeout=timeout_s)
        light.update(part)
        clouds.update(drawn or {})

    def refine(states: np.ndarray, sides: dict[str, bool]) -> dict[str, PhaseRefinement]:
        futures = [pools.submit_to(k, refine_part, key, states, sides) for k in shares]
        return {n: r for f in futures for n, r in f.result(timeout=timeout_s).items()}

    est = decode_walk({n: light[n] for n in names}, refine=refine, earlier=earlier)
    result = json_safe(est.to_result(first_index=indices[0]))
    for frame, index in zip(result["frames"], indices):
        frame["index"] = int(index)
    seconds = time.perf_counter() - t0
    bundle = None
    if bundle_from is not None:  # registration for display is done later (register_stage)
        bundle = make_bundle(tracks, est, None, indices, image_size, from_frame=bundle_from,
                             register=False, clouds=clouds)
    return result, bundle, seconds, est


def predict_feedback(est: WalkEstimate, tracks: dict[str, CameraTrack], indices: list[int],
                     image_size: dict[str, tuple[int, int]], n_ahead: int, skip: int = 0
                     ) -> dict[str, list[tuple[int, tuple[int, int, int, int], np.ndarray]]]:
    """Priors for ``n_ahead`` frames from ``skip`` frames after a live window (§7.1), in a worker.

    Per camera ``(frame index, full-frame box, soft mask crop)``; the renderer
    is made once per worker process.
    """
    from estimator.prior import FEEDBACK, predict_priors

    # Predictions count frames on from the window's last one (a window may hold an
    # index gap, see WindowBuffer; the extrapolation is per frame of the window).
    priors = predict_priors(est, tracks, image_size, n_ahead, renderer=_get_renderer(),
                            first_index=indices[-1] + 1 - len(indices), skip=skip, config=FEEDBACK)
    return {cam: [(p.frame_index, tuple(int(v) for v in p.box), p.mask) for p in ps]
            for cam, ps in priors.items()}


def update_rig(acc: RigAccumulator, est: WalkEstimate, indices: list[int], calibrate: bool,
               keypoints: dict[str, np.ndarray] | None = None,
               viewpoints: dict[str, tuple[float, float]] | None = None
               ) -> tuple[RigAccumulator, dict | None, dict | None]:
    """Add a live window's postures (or the agents' ``keypoints``, :meth:`RigAccumulator.add`) to a
    rig's accumulator and, if asked, calibrate it (in a worker): ``(accumulator, calibration or None,
    pinhole cameras for Rerun or None)``, the latter two with the newest frame's posture of the
    person (``person``); the accumulator travels to the worker and back, so that the service process
    holds the state and the worker none. ``indices``: the window's frame indices; ``viewpoints``: the
    rig's smoothed viewpoints (:meth:`RigAccumulator.calibrate`)."""
    acc.add(est, indices[0], keypoints, indices=np.asarray(indices))
    if not calibrate:
        return acc, None, None
    rig = acc.calibrate(viewpoints)
    newest = acc.newest_posture(rig)
    person = None if newest is None else {"frame_index": newest[0], "joints3d": np.round(newest[1], 4).tolist()}
    arrays = rig_arrays(rig)
    if arrays is not None and newest is not None:
        arrays["person"] = newest
    return acc, json_safe({"source": rig.source, "frames": acc.n_frames, "windows": acc.windows,
                           "postures": "keypoints" if acc.from_keypoints else "mnbp",
                           "calibration": rig.to_dict(), "body": rig.body_dict(), "person": person,
                           "notes": rig.notes}), arrays


# ---------------------------------------------------------------------------- batch jobs


def run_job(job_id: str, db_url: str, kind: str, input_dir: str, options: dict[str, Any],
            *, want_bundle: bool = False, claim: str | None = None) -> list[StageBundle] | None:
    """Run one claimed job to its end (in a worker).

    The recording is estimated window by window, one segment per heading of
    the walker (:func:`estimator.windows.segment_walk`, with ``options["windows"]``:
    ``length``, ``hop``, ``threshold_deg``, ``confirm``), each segment's 2D
    postures measured by mNBP unless ``options["posture"]`` is ``"model"``
    (:func:`estimator.mnbp.measure_postures`), and the rig and the person's
    posture calibrated from them at ``options["height_m"]``
    (:func:`estimator.rig.calibrate_rig`). Writes progress and the
    result (or the failure) to the store itself, as the run holding ``claim``
    (every write is refused, and the run stops, once the job was cancelled or
    re-queued: :meth:`JobStore.claimed`); raises nothing for bad input.
    Returns the stage bundles (one per segment) for Rerun when asked and done.
    """
    store = _store(db_url).claimed(claim)
    decoding: dict[str, dict[str, int]] = {}  # videos: frames decoded vs the header's count
    try:
        store.report(job_id, 0.05, "reading input")
        if kind == "sequence":
            seq = read_sequence(input_dir)
            store.report(job_id, 0.3, "building tracks")
            tracks = tracks_from_sequence(seq)
            timeline = index_frames({c: seq.n_frames for c in seq.cameras})
            image_size = {c: tuple(seq.image_size) for c in seq.cameras}
            fps = seq.fps
            truth = seq.truth
        elif kind == "videos":
            from capture.segment import default_warmup

            # One warm-up for all of the job's videos (staging counted their frames).
            warmup = options.get("warmup") or default_warmup(int(options.get("n_frames") or 0))
            tracks, rates, info = video_tracks(
                Path(input_dir), warmup=warmup, report=lambda p, s: store.report(job_id, 0.05 + 0.4 * p, s),
                options=options)
            segmentations, image_size, decoding = info["segmentations"], info["sizes"], info["decoding"]
            store.report(job_id, 0.45, "synchronising the videos")
            tracks, fps, sync, timeline = sync_videos(tracks, rates, _get_model(), options.get("sync", "auto"))
            first = FirstPass(Path(input_dir), segmentations, warmup, sync_shifted(sync),
                              int(options.get("max_frames") or 0) or None)
            truth = None
        else:
            raise ValueError(f"unknown job kind {kind!r}")
        tracks = pad_tracks(tracks)
        store.report(job_id, 0.5, "estimating")
        model = _get_model()
        t0 = time.perf_counter()
        posture = MNBPConfig() if options.get("posture", "mnbp") == "mnbp" else None
        rig = RigConfig(height_m=float(options.get("height_m", 1.75)))
        keypoints = None
        if options.get("keypoints_dir"):  # a detector's keypoints calibrate the rig (checked when staged)
            keypoints = keypoints_on_timeline(read_keypoints([Path(options["keypoints_dir"])]), timeline)
            posture, rig = None, RigConfig.for_keypoints(height_m=rig.height_m)
        # the feedback pass re-segments for the viewpoints, postures and rig; a detector's keypoints give
        # the last two in its place
        feedback = kind == "videos" and options.get("feedback", "on") == "on" and keypoints is None
        span = 0.15 if feedback else 0.4  # of the progress, per estimate (with feedback: 0.5, 0.65-0.75, 0.75)

        def estimate(estimated: dict[str, CameraTrack], start: float) -> SegmentedWalk:
            nonlocal tracks
            tracks = estimated  # the tracks of the walk returned (Rerun's bundles)
            return segment_walk(estimated, model, **options.get("windows", {}), posture=posture, rig=rig,
                                keypoints=keypoints,
                                progress=lambda f: store.report(job_id, start + span * f, "estimating"))

        walk = estimate(tracks, 0.5)
        passes, fed = None, None
        if feedback:
            store.report(job_id, 0.65, "segmenting again with the model's feedback (§7.1)")
            walk, fed, passes = feedback_pass(
                first, model, walk, lambda t: estimate(t, 0.75),
                progress=lambda f: store.report(job_id, 0.65 + 0.1 * f, "segmenting again with the model's "
                                                                        "feedback (§7.1)"))
        store.report(job_id, 0.9, "writing result")
        result = add_feedback(json_safe(walk.to_result()), fed)
        result["fps"] = fps
        if kind == "videos" and sync is not None:
            result["sync"] = sync
        _mark_decoding(result, decoding)
        result["timing"] = {"estimate_s": round(time.perf_counter() - t0, 4)}
        if truth is not None and "cameras" in truth:
            result["truth_cameras"] = {
                c: {k: v for k, v in t.items() if k in ("azimuth_deg", "elevation_deg")}
                for c, t in truth["cameras"].items()}
        refined = None
        if options.get("refine") and kind == "videos" and sync_shifted(sync):
            result["notes"].append("refine: not done on videos paired by their offsets (sync); the videos' "
                                   "own frames are what the second pass segments")
        elif options.get("refine") and fed is not None and passes is None:
            result["notes"].append(f"refine: not done, as the feedback pass: {fed['note']}")
        elif options.get("refine"):
            store.report(job_id, 0.92, "refining silhouettes (model feedback)")
            if kind == "sequence":
                refined = _refine_sequence(seq, model, walk)
            else:  # the feedback pass's, from which the result was estimated, or one made now
                from capture.refine import refined_sequence

                refined = refined_sequence(passes if passes is not None else _second_pass(first, model, walk), fps)
            out = Path(options["refined_dir"])
            write_sequence(out / "silhouettes", refined.sequence)
            shutil.make_archive(str(out / "silhouettes"), "zip", out / "silhouettes")
            shutil.rmtree(out / "silhouettes")  # the zip is what is served
            result["refined"] = {"silhouettes": f"/v1/jobs/{job_id}/silhouettes",
                                 "priors": refined.n_priors,
                                 "changed_pixels": refined.changed_pixels}
        bundles = None
        if want_bundle:
            views = feedback_views(refined) if refined is not None else {}
            bundles = []
            for seg in walk.segments:
                if seg.estimate is None:
                    continue
                b = make_bundle(window_tracks(tracks, seg.start, seg.stop), seg.estimate, model,
                                list(range(seg.start, seg.stop)), image_size, from_frame=seg.first - seg.start)
                b.extra["feedback"] = {cam: v[seg.start:seg.stop] for cam, v in views.items()}
                bundles.append(b)
        if not store.finish(job_id, result):
            return None  # cancelled or deleted meanwhile
        return bundles
    except JobGone:
        return None
    except (ValueError, OSError) as exc:  # SequenceError, unreadable video, nothing to estimate
        store.fail(job_id, str(exc))
        return None
    except Exception as exc:  # a bug: record it on the job, keep the worker alive
        store.fail(job_id, f"internal error: {type(exc).__name__}: {exc}")
        raise


def sync_shifted(sync: dict[str, Any] | None) -> bool:
    """Whether synchronisation paired the videos' frames other than by index."""
    if sync is None:
        return False
    cams = sync["cameras"].values()
    return len({c["fps"] for c in cams}) > 1 or any(abs(c["offset_frames"] or 0.0) >= 0.5 for c in cams)


def _refine_sequence(seq: Sequence, model: AppearanceModel, estimate: SegmentedWalk):
    """The job's sequence's silhouettes fused with priors from the job's ``estimate``."""
    from capture.refine import refine_sequence

    return refine_sequence(seq, model, renderer=_get_renderer(), estimate=estimate)


@dataclass(frozen=True)
class FirstPass:
    """What the feedback pass needs of a recording's first segmentation (:func:`feedback_pass`)."""

    folder: Path  # the videos, one per camera
    segmentations: dict[str, list]  # per camera, as :func:`capture.refine.segment` returned them
    warmup: int
    shifted: bool = False  # frames paired other than by index (:func:`sync_shifted`)
    max_frames: int | None = None  # per video, as the first pass decoded (None: all)


def _second_pass(first: FirstPass, model: AppearanceModel, walk: SegmentedWalk,
                 progress: Callable[[float], None] | None = None):
    """The videos segmented once more, with priors rendered from ``walk``; ``first`` is the first
    pass (:func:`capture.refine.refine_cameras`; a :class:`capture.refine.RefineResult`)."""
    from capture.refine import plates_for, refine_cameras, video_frames
    from capture.segment import SegmentSettings

    videos = {c: p for c, p in list_videos(first.folder).items() if c in first.segmentations}  # not those left out
    return refine_cameras({c: video_frames(p, first.max_frames) for c, p in videos.items()},
                          model, renderer=_get_renderer(), settings=SegmentSettings(warmup_frames=first.warmup),
                          raw=first.segmentations, estimate=walk, progress=progress, plates=plates_for(videos))


def add_feedback(result: dict, block: dict | None) -> dict:
    """``result`` with the feedback pass's ``block`` (:func:`feedback_pass`) and its note, if one ran."""
    if block is not None:
        result["feedback"] = block
        result["notes"].append(block["note"])
    return result


def feedback_pass(first: FirstPass, model: AppearanceModel, walk: SegmentedWalk,
                  estimate: Callable[[dict[str, CameraTrack]], SegmentedWalk],
                  progress: Callable[[float], None] | None = None) -> tuple[SegmentedWalk, dict, Any]:
    """Izo–Grimson §7.1 on recorded videos: each video segmented again with the model rendered
    from ``walk`` (the first estimate) as a foreground prior (:func:`_second_pass`; cameras
    whose estimate fails the trust test get none), then estimated again by ``estimate``.

    Not done where ``first.shifted`` (the second pass segments each video's own frames).
    Returns the walk (the first one whenever the pass or the second estimate cannot be done:
    it never fails what the first estimate gave), the result's ``feedback`` block (``done``,
    ``priors``, ``changed_pixels``, ``note``) and the :class:`capture.refine.RefineResult`
    (None when not segmented again). ``progress`` gets the fraction of the videos segmented
    again. Measured on walkers composited into real footage (docs/ROBUSTNESS.md).
    """
    from capture.refine import changed_pixels, track_from_segmentations

    if first.shifted:
        return walk, {"done": False, "note": "feedback: not done on videos paired by their offsets (sync); "
                                             "the videos' own frames are what the second pass segments"}, None
    try:
        passes = _second_pass(first, model, walk, progress)
    except ValueError as exc:  # e.g. a camera whose video holds no walker at all
        return walk, {"done": False, "note": f"feedback: not done ({exc}); the first estimate stands"}, None
    priors = sum(len(v) for v in passes.priors.values())
    block = {"done": False, "priors": priors,
             "changed_pixels": sum(changed_pixels(passes.raw[c], passes.refined[c]) for c in passes.refined)}
    if priors == 0:
        return walk, {**block, "note": "feedback: no camera's estimate passed the trust test; the first "
                                       "estimate stands"}, passes
    try:  # crops as the first pass's (cameras of any size keep their full frame)
        second = estimate(pad_tracks({c: track_from_segmentations(s) for c, s in passes.refined.items()}))
    except ValueError as exc:
        return walk, {**block, "note": f"feedback: the second estimate failed ({exc}); the first estimate "
                                       "stands"}, passes
    return second, {**block, "done": True,
                    "note": f"silhouettes segmented again with the model's feedback (Izo-Grimson §7.1; {priors} "
                            f"priors, {block['changed_pixels']} pixels changed), then estimated again"}, passes


def feedback_views(refined) -> dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]]:
    """Per camera and frame of a :class:`capture.refine.RefinedSequence`: raw silhouette,
    prior and refined silhouette cut to the union of their boxes, so that they line up
    side by side (Rerun)."""
    seq = refined.sequence
    out: dict[str, list] = {}
    for cam in seq.cameras:
        out[cam] = []
        for k, done in enumerate(seq.silhouettes[cam]):
            raw = refined.raw_frame(cam, k)
            if raw is None:
                out[cam].append(None)
                continue
            layers = [raw, refined.prior_frame(cam, k), done if done is not None and done.shape == raw.shape
                      else None]
            layers = [np.zeros_like(raw) if x is None else x for x in layers]
            box = crop_to_box(np.maximum.reduce(layers))
            if box is None:
                out[cam].append(None)
                continue
            x, y, w, h = (int(v) for v in box[1])
            out[cam].append(tuple(layer[y:y + h, x:x + w] for layer in layers))
    return out


def video_tracks(folder: Path, *, warmup: int | None, report, options: dict[str, Any] | None = None
                 ) -> tuple[dict[str, CameraTrack], dict[str, float], dict[str, Any]]:
    """Each video of ``folder`` segmented (:func:`_segment_videos`) as a camera track (not padded:
    recordings differ in length), each camera's frame rate (the container's, else the first
    video's, else 15) and ``{"decoding", "sizes", "warmup", "fps"}``. ``warmup`` None: the
    default for the shortest video's announced frame count."""
    from capture.refine import track_from_segmentations
    from capture.segment import default_warmup

    options = dict(options or {})
    counts = options.get("header_frames")
    if counts is None:
        counts = {}
        for path in list_videos(folder).values():
            with _open_video(path) as source:
                counts[path.stem] = source.frame_count() or 0
        options["header_frames"] = counts
    warmup = warmup or default_warmup(int(min(counts.values(), default=0)))
    segmentations, sizes, fps, decoding = _segment_videos(folder, warmup=warmup, report=report, options=options)
    tracks = {c: track_from_segmentations(s) for c, s in segmentations.items()}
    rates = {c: float(decoding[c].get("fps") or fps) for c in tracks}
    return tracks, rates, {"decoding": decoding, "sizes": sizes, "warmup": warmup, "fps": fps,
                           "segmentations": segmentations}


def sync_videos(tracks: dict[str, CameraTrack], rates: dict[str, float], model: AppearanceModel, mode: str
                ) -> tuple[dict[str, CameraTrack], float, dict[str, Any] | None, dict[str, np.ndarray]]:
    """Recorded videos on one timeline (``mode`` "auto": offsets from the walk,
    :func:`estimator.sync.sync_tracks`; "off": frames paired by index, the first video's
    rate): the tracks (padded), the timeline's rate, the result's ``sync`` block and each
    camera's own frame at each frame of the timeline (-1 where it has none;
    :func:`estimator.sync.timeline_frames`), by which a detector's keypoints follow."""
    if mode not in ("auto", "off"):
        raise ValueError(f"sync must be 'auto' or 'off', got {mode!r}")
    if mode == "off" or len(tracks) < 2:
        return (pad_tracks(tracks), next(iter(rates.values()), 15.0), None,
                index_frames({c: len(t.silhouettes) for c, t in tracks.items()}))
    aligned, rate, result, frames = sync_tracks(tracks, rates, model)
    return pad_tracks(aligned), rate, result.to_dict(), frames


class DamagedVideo(ValueError):
    """A video of the input that cannot be opened or decodes too little: bad input (a job fails
    naming it, ``posecal estimate`` exits 2), not a computation that failed."""


def _open_video(path: Path):
    """``path`` as a :class:`capture.sources.VideoFileSource`; :class:`DamagedVideo` naming it when
    it cannot be opened."""
    from capture.sources import SourceError, VideoFileSource

    try:
        return VideoFileSource(path)
    except SourceError as exc:
        raise DamagedVideo(f"video {path.name}: {exc}") from None


def _segment_videos(folder: Path, *, warmup: int, report, options: dict[str, Any] | None = None
                    ) -> tuple[dict[str, list], dict, float, dict[str, dict[str, int]]]:
    """Background subtraction (:func:`capture.refine.segment`) over each ``<camera>.<ext>`` video.

    Returns the segmentations per camera, the frame sizes, the frame rate (the first
    video's) and per camera ``{"decoded_frames", "header_frames", "fps"}`` (its own rate,
    None when the container does not say). At most ``options["max_frames"]``
    frames are decoded per video (a header can lie). A video that decodes no frame, or
    fewer than its header counts and fewer than one window (``options["windows"]["length"]``),
    is damaged: it is left out (its ``decoding`` entry says why, ``"left_out"``) and the
    other cameras go on; :class:`DamagedVideo` naming every video when none is left.
    """
    from capture.refine import background_note, plate_path, segment_clip, video_frames
    from capture.segment import SegmentSettings
    from capture.sources import read_plate

    options = options or {}
    max_frames = int(options.get("max_frames") or 0) or None
    header_frames = options.get("header_frames") or {}
    min_frames = int((options.get("windows") or {}).get("length") or 1)
    videos = list(list_videos(folder).values())
    settings = SegmentSettings(warmup_frames=warmup)
    segmentations, sizes, decoding, fps = {}, {}, {}, 0.0
    for i, path in enumerate(videos):
        with _open_video(path) as source:
            rate = float(source.fps or 0.0)
            header = int(header_frames.get(path.stem) or source.frame_count() or 0)
            size = source.size
        plate_file = plate_path(path)
        try:
            plate = None if plate_file is None else read_plate(plate_file, size)
        except ValueError as exc:
            raise DamagedVideo(str(exc)) from None
        segs, chosen = segment_clip(video_frames(path, max_frames), settings, plate=plate)
        decoding[path.stem] = {"decoded_frames": len(segs), "header_frames": header,
                               "fps": round(rate, 4) or None}
        if chosen:
            decoding[path.stem]["walker"] = chosen
        background = background_note(segs, plate_file)
        if background:
            decoding[path.stem]["background"] = background
        report((i + 1) / len(videos), f"segmented {path.name}")
        if not segs:
            decoding[path.stem]["left_out"] = f"video {path.name} has no decodable frames"
        elif header and len(segs) < header and len(segs) < min_frames:
            decoding[path.stem]["left_out"] = (
                f"video {path.name}: only {len(segs)} of the {header} frames its header counts decode, fewer "
                f"than one window ({min_frames} frames): truncated or damaged")
        else:
            segmentations[path.stem], sizes[path.stem] = segs, size
            fps = fps or rate
    if not segmentations:
        raise DamagedVideo("; ".join(d["left_out"] for d in decoding.values()) or f"no videos in {folder}")
    return segmentations, sizes, fps or 15.0, decoding


def _mark_decoding(result: dict[str, Any], decoding: dict[str, dict[str, int]]) -> None:
    """Each video camera's decoded and announced frame counts in ``result["cameras"]``, a note
    (camera and top level) for a video that decoded fewer frames than its header counts, and one
    (top level) for each video left out as damaged (:func:`_segment_videos`)."""
    for cam, counts in decoding.items():
        if "left_out" in counts:
            result.setdefault("notes", []).append(f"{cam}: left out, {counts['left_out']}; estimated from the "
                                                  "other cameras")
            continue
        entry = result.get("cameras", {}).get(cam)
        said = [counts[k] for k in ("walker", "background") if counts.get(k)]
        if entry is not None:
            entry.update({k: v for k, v in counts.items() if k not in ("walker", "background")})
            if said:
                entry.setdefault("notes", []).extend(said)
        if said:
            result.setdefault("notes", []).extend(f"{cam}: {note}" for note in said)
        decoded, header = counts["decoded_frames"], counts["header_frames"]
        if header and decoded != header:
            note = (f"{cam}: {decoded} frames decoded, its video's header counts {header}: "
                    "truncated or damaged; estimated from the frames that decoded")
            if entry is not None:
                entry.setdefault("notes", []).append(note)
            result.setdefault("notes", []).append(note)
