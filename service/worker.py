"""CPU work of the service: upload intake, batch jobs and window estimation.

Everything heavy runs in worker processes (:func:`make_pool`) that load the
appearance model once (:func:`init_worker`). The event loop only awaits
futures. Two entry points run in the pool:

- :func:`run_job`: read the staged input (sequence folder or videos), build the
  camera tracks, estimate them window by window with one segment per heading
  (:func:`~estimator.windows.segment_walk`), write the result to the job store,
  writing progress as it goes;
- :func:`estimate_window`: one live window;
- :func:`predict_feedback`: priors for the frames after a live window (§7.1).

Both can return a :class:`StageBundle`: the plain arrays of every stage that
:mod:`service.rerun_log` draws (inputs, registration, matched cluster means,
viewpoint clouds, phase observations, HMM path, joints).

:func:`stage_upload` runs in the API's thread pool when a job is submitted: it
unpacks and validates the upload so a bad one is answered with a 4xx at once.
"""

from __future__ import annotations

import concurrent.futures
import concurrent.futures.process
import logging
import multiprocessing
import os
import shutil
import threading
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from estimator.appearance import AppearanceModel, load_model
from estimator.mnbp import MNBPConfig
from estimator.pipeline import (CameraTrack, WalkEstimate, crop_to_box, estimate_walk, pad_tracks,
                                tracks_from_sequence)
from estimator.rig import RigConfig
from estimator.sequence import Sequence, SequenceError, read_sequence, write_sequence
from estimator.windows import SegmentedWalk, segment_walk, window_tracks

from .jobs import JobGone, JobStore

__all__ = [
    "StageBundle",
    "UploadError",
    "WorkerPool",
    "estimate_window",
    "predict_feedback",
    "init_worker",
    "make_pool",
    "run_job",
    "stage_upload",
]

log = logging.getLogger(__name__)

VIDEO_EXTENSIONS = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v")
_MAX_ZIP_MEMBERS = 200_000
_MAX_CLOUD = 1500  # viewpoint-cloud points kept per camera for drawing
_NAME_OK = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-")


# ----------------------------------------------------------------------- upload intake


class UploadError(ValueError):
    """A rejected upload: ``status`` is the HTTP code, ``str()`` the reason."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status


@dataclass(frozen=True)
class StagedInput:
    """A validated job input on disk."""

    kind: str  # "sequence" | "videos"
    path: Path  # the sequence folder, or the folder of <camera>.<ext> videos
    cameras: list[str]
    n_frames: int


def stage_upload(files: list[tuple[str, BinaryIO]], job_dir: Path, *, limit_bytes: int,
                 max_frames: int) -> StagedInput:
    """Unpack and validate an upload into ``job_dir``; raise :class:`UploadError` if bad.

    ``files`` are ``(filename, file object)``: one ``.zip`` holding a sequence
    folder (``rig.json`` at its top or in its single top folder), or one video
    per camera named ``<camera>.<ext>``.
    """
    if not files:
        raise UploadError(422, "no files uploaded: send one zipped sequence folder or one video per camera")
    job_dir.mkdir(parents=True, exist_ok=True)
    names = [Path(name or "").name for name, _ in files]
    if len(files) == 1 and names[0].lower().endswith(".zip"):
        return _stage_zip(files[0][1], job_dir, limit_bytes=limit_bytes, max_frames=max_frames)
    if all(n.lower().endswith(VIDEO_EXTENSIONS) for n in names):
        return _stage_videos(files, job_dir, max_frames=max_frames)
    raise UploadError(415, f"expected one .zip sequence folder or videos ({', '.join(VIDEO_EXTENSIONS)}), "
                           f"got {names}")


def _stage_zip(fh: BinaryIO, job_dir: Path, *, limit_bytes: int, max_frames: int) -> StagedInput:
    try:
        zf = zipfile.ZipFile(fh)
    except (zipfile.BadZipFile, OSError) as exc:
        raise UploadError(400, f"the upload is not a readable zip file: {exc}") from None
    with zf:
        members = zf.infolist()
        if not members:
            raise UploadError(422, "the zip file is empty")
        if len(members) > _MAX_ZIP_MEMBERS:
            raise UploadError(413, f"the zip holds {len(members)} files, more than {_MAX_ZIP_MEMBERS}")
        if sum(m.file_size for m in members) > 4 * limit_bytes:
            raise UploadError(413, "the zip expands to more than 4x the upload limit")
        out = job_dir / "input"
        root = out.resolve()
        for m in members:
            target = (out / m.filename).resolve()
            if not target.is_relative_to(root):
                raise UploadError(400, f"zip member {m.filename!r} points outside the archive")
        bad = None
        try:
            bad = zf.testzip()
            zf.extractall(out)
        except (zipfile.BadZipFile, OSError, EOFError, NotImplementedError) as exc:
            raise UploadError(400, f"corrupt zip file: {exc}") from None
        if bad is not None:
            raise UploadError(400, f"corrupt zip file: bad CRC in {bad}")
    folder = _find_sequence_root(out)
    try:
        seq = read_sequence(folder)
    except SequenceError as exc:
        raise UploadError(422, str(exc).replace(str(out) + os.sep, "")) from None
    if seq.n_frames > max_frames:
        raise UploadError(413, f"{seq.n_frames} frames per camera exceed the limit of {max_frames}")
    if all(s is None or not s.any() for sils in seq.silhouettes.values() for s in sils):
        raise UploadError(422, "the sequence holds no silhouette pixels")
    return StagedInput("sequence", folder, list(seq.cameras), seq.n_frames)


def _find_sequence_root(out: Path) -> Path:
    if (out / "rig.json").is_file():
        return out
    tops = [p for p in out.iterdir() if p.name != "__MACOSX"]
    if len(tops) == 1 and tops[0].is_dir() and (tops[0] / "rig.json").is_file():
        return tops[0]
    raise UploadError(422, "no rig.json at the top of the zip (or in its single top folder): "
                           "zip a sequence folder, see docs/FORMATS.md")


def _stage_videos(files: list[tuple[str, BinaryIO]], job_dir: Path, *, max_frames: int) -> StagedInput:
    import cv2

    folder = job_dir / "videos"
    folder.mkdir(parents=True, exist_ok=True)
    cameras, sizes, counts = [], {}, {}
    for name, fh in files:
        path = Path(Path(name).name)
        cam = path.stem
        if not cam or not set(cam) <= _NAME_OK or len(cam) > 64:
            raise UploadError(422, f"video {path.name!r}: the file name (without extension) is the "
                                   "camera name and must match [A-Za-z0-9_.-]{1,64}")
        if cam in cameras:
            raise UploadError(422, f"two videos for camera {cam!r}")
        target = folder / f"{cam}{path.suffix.lower()}"
        with open(target, "wb") as out:
            shutil.copyfileobj(fh, out, 1 << 20)
        cap = cv2.VideoCapture(str(target))
        try:
            ok, frame = cap.read() if cap.isOpened() else (False, None)
            if not ok or frame is None:
                raise UploadError(422, f"video {path.name!r} cannot be decoded")
            n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            cap.release()
        cameras.append(cam)
        sizes[cam] = (frame.shape[1], frame.shape[0])
        counts[cam] = n
    if len(set(sizes.values())) != 1:
        raise UploadError(422, f"videos of one rig must have the same frame size, got {sizes}")
    if max(counts.values()) > max_frames:
        raise UploadError(413, f"{max(counts.values())} frames per camera exceed the limit of {max_frames}")
    return StagedInput("videos", folder, cameras, max(counts.values()))


# ---------------------------------------------------------------------------- the pool

_model: AppearanceModel | None = None
_stores: dict[str, JobStore] = {}
_renderer = None  # estimator.render.Renderer, made on first use (feedback priors)


def make_pool(n: int, model_path: Path | None, *, renderer: bool = False) -> WorkerPool:
    """A process pool whose workers hold the model (unless ``model_path`` is None) and a
    renderer for feedback priors (if asked); started (spawn), warmed up, and replaced if
    a worker dies.

    BLAS is kept to one thread per worker: the eq. 8 product is small, and
    OpenBLAS threads spinning against each other on a shared 2-core host made
    it ~6x slower.
    """
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")

    def start() -> concurrent.futures.ProcessPoolExecutor:
        pool = concurrent.futures.ProcessPoolExecutor(
            max_workers=n, mp_context=multiprocessing.get_context("spawn"),
            initializer=init_worker, initargs=(None if model_path is None else str(model_path), renderer))
        for f in [pool.submit(_ping) for _ in range(n)]:
            f.result()
        return pool

    return WorkerPool(start)


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


def init_worker(model_path: str | None, renderer: bool = False) -> None:
    """Pool initializer: load the model once per process (if given; and open the renderer)."""
    global _model
    import cv2

    cv2.setNumThreads(1)
    if model_path is not None:
        _model = load_model(model_path)
    if renderer:
        _get_renderer()


def _ping() -> int:
    return os.getpid()


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
    if url not in _stores:
        _stores[url] = JobStore(url)
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


def make_bundle(tracks: dict[str, CameraTrack], est: WalkEstimate, model: AppearanceModel,
                indices: list[int], image_size: dict[str, tuple[int, int]], *,
                from_frame: int = 0, register: bool = True, rng: int = 0) -> StageBundle:
    """Collect what :mod:`service.rerun_log` draws; frames before ``from_frame`` (position
    in the window) are left out of the per-frame images (already drawn).

    With ``register`` False the registered silhouettes and cluster means are left
    empty, for :func:`register_stage` to fill later (off the live latency path).
    """
    gen = np.random.default_rng(rng)
    clouds = {}
    offsets = model.member_offsets
    for name in tracks:
        labels = est.cameras[name].labels
        matched = labels[labels >= 0]
        if matched.size:
            idx = np.concatenate([np.arange(offsets[k], offsets[k + 1]) for k in matched])
            if idx.size > _MAX_CLOUD:
                idx = gen.choice(idx, _MAX_CLOUD, replace=False)
            clouds[name] = np.stack([model.member_azimuth_deg[idx], model.member_elevation_deg[idx]], -1)
        else:
            clouds[name] = np.zeros((0, 2))
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


def _rig_extra(est: WalkEstimate) -> dict[str, Any]:
    """The person's posture and the pinhole rig, as plain arrays, when the estimate has them."""
    rig = est.rig
    out: dict[str, Any] = {}
    if rig is not None and rig.joints3d is not None:
        out["person"] = np.asarray(rig.joints3d, float)
    if rig is not None and rig.centres_m is not None:
        out["rig"] = {"cameras": list(rig.cameras), "reference": rig.reference,
                      "rotations": np.asarray(rig.rotations, float),
                      "centres_m": np.asarray(rig.centres_m, float), "focal_px": np.asarray(rig.focal_px, float),
                      "walker_m": np.asarray(rig.walker_m, float)}
    return out


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
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if isinstance(value, np.generic):
        return json_safe(value.item())
    return value


# ---------------------------------------------------------------------------- live windows


def estimate_window(tracks: dict[str, CameraTrack], indices: list[int],
                    image_size: dict[str, tuple[int, int]], *, bundle_from: int | None = None,
                    keep_estimate: bool = False
                    ) -> tuple[dict, StageBundle | None, float, WalkEstimate | None]:
    """Estimate one live window (in a worker): ``(result, bundle, seconds, estimate)``.

    The bundle is None unless ``bundle_from`` is given; the estimate itself is
    returned only with ``keep_estimate`` (for :func:`predict_feedback`).
    """
    model = _get_model()
    t0 = time.perf_counter()
    est = estimate_walk(tracks, model)
    result = json_safe(est.to_result(first_index=indices[0]))
    for frame, index in zip(result["frames"], indices):
        frame["index"] = int(index)
    seconds = time.perf_counter() - t0
    bundle = None
    if bundle_from is not None:  # registration for display is done later (register_stage)
        bundle = make_bundle(tracks, est, model, indices, image_size, from_frame=bundle_from,
                             register=False)
    return result, bundle, seconds, est if keep_estimate else None


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


# ---------------------------------------------------------------------------- batch jobs


def run_job(job_id: str, db_url: str, kind: str, input_dir: str, options: dict[str, Any],
            *, want_bundle: bool = False) -> list[StageBundle] | None:
    """Run one claimed job to its end (in a worker).

    The recording is estimated window by window, one segment per heading of
    the walker (:func:`estimator.windows.segment_walk`, with ``options["windows"]``:
    ``length``, ``hop``, ``threshold_deg``, ``confirm``), each segment's 2D
    postures measured by mNBP unless ``options["posture"]`` is ``"model"``
    (:func:`estimator.mnbp.measure_postures`), and the rig and the person's
    posture calibrated from them at ``options["height_m"]``
    (:func:`estimator.rig.calibrate_rig`). Writes progress and the
    result (or the failure) to the store itself; raises nothing for bad input.
    Returns the stage bundles (one per segment) for Rerun when asked and done.
    """
    store = _store(db_url)
    try:
        store.report(job_id, 0.05, "reading input")
        if kind == "sequence":
            seq = read_sequence(input_dir)
            store.report(job_id, 0.3, "building tracks")
            tracks = tracks_from_sequence(seq)
            image_size = {c: tuple(seq.image_size) for c in seq.cameras}
            fps = seq.fps
            truth = seq.truth
        elif kind == "videos":
            from capture.refine import track_from_segmentations
            from capture.segment import default_warmup

            # One warm-up for all of the job's videos (staging counted their frames).
            warmup = options.get("warmup") or default_warmup(int(options.get("n_frames") or 0))
            segmentations, image_size, fps = _segment_videos(
                Path(input_dir), warmup=warmup, report=lambda p, s: store.report(job_id, 0.05 + 0.45 * p, s))
            tracks = {c: track_from_segmentations(s) for c, s in segmentations.items()}
            truth = None
        else:
            raise ValueError(f"unknown job kind {kind!r}")
        tracks = pad_tracks(tracks)
        store.report(job_id, 0.5, "estimating")
        model = _get_model()
        t0 = time.perf_counter()
        posture = MNBPConfig() if options.get("posture", "mnbp") == "mnbp" else None
        rig = RigConfig(height_m=float(options.get("height_m", 1.75)))
        walk = segment_walk(tracks, model, **options.get("windows", {}), posture=posture, rig=rig,
                            progress=lambda f: store.report(job_id, 0.5 + 0.4 * f, "estimating"))
        store.report(job_id, 0.9, "writing result")
        result = json_safe(walk.to_result())
        result["fps"] = fps
        result["timing"] = {"estimate_s": round(time.perf_counter() - t0, 4)}
        if truth is not None and "cameras" in truth:
            result["truth_cameras"] = {
                c: {k: v for k, v in t.items() if k in ("azimuth_deg", "elevation_deg")}
                for c, t in truth["cameras"].items()}
        refined = None
        if options.get("refine"):
            store.report(job_id, 0.92, "refining silhouettes (model feedback)")
            refined = (_refine_sequence(seq, model, walk) if kind == "sequence" else
                       _refine_videos(Path(input_dir), model, fps, walk, segmentations, warmup))
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


def _refine_sequence(seq: Sequence, model: AppearanceModel, estimate: SegmentedWalk):
    """The job's sequence's silhouettes fused with priors from the job's ``estimate``."""
    from capture.refine import refine_sequence

    return refine_sequence(seq, model, renderer=_get_renderer(), estimate=estimate)


def _refine_videos(folder: Path, model: AppearanceModel, fps: float, estimate: SegmentedWalk,
                   segmentations: dict, warmup: int):
    """The videos segmented once more, with priors from the job's ``estimate``; the job's
    own segmentations are the first pass (``capture.refine.refine_videos``)."""
    from capture.refine import refine_videos

    videos = {p.stem: p for p in sorted(folder.iterdir()) if p.suffix.lower() in VIDEO_EXTENSIONS}
    return refine_videos(videos, model, renderer=_get_renderer(), warmup=warmup, fps=fps,
                         raw=segmentations, estimate=estimate)


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


def _segment_videos(folder: Path, *, warmup: int, report) -> tuple[dict[str, list], dict, float]:
    """Background subtraction (:func:`capture.refine.segment`) over each ``<camera>.<ext>`` video.

    Returns the segmentations per camera, the frame sizes and the frame rate.
    """
    from capture.refine import segment
    from capture.segment import SegmentSettings
    from capture.sources import VideoFileSource

    videos = sorted(p for p in folder.iterdir() if p.suffix.lower() in VIDEO_EXTENSIONS)
    settings = SegmentSettings(warmup_frames=warmup)
    segmentations, sizes, fps = {}, {}, 0.0
    for i, path in enumerate(videos):
        with VideoFileSource(path) as source:
            fps = fps or source.fps or 0.0
            sizes[path.stem] = source.size
            segs = segment((frame.image for frame in source), settings)
        if not segs:
            raise ValueError(f"video {path.name} has no decodable frames")
        segmentations[path.stem] = segs
        report((i + 1) / len(videos), f"segmented {path.name}")
    return segmentations, sizes, fps or 15.0
