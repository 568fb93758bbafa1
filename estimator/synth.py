"""Synthetic multi-camera walking sequences with ground truth.

A walker of random size and style (or driven by a motion-capture recording)
walks a straight line along the world x axis; fixed cameras at random
viewpoints (the paper's range) look at the middle of the path. The result is a
:class:`~estimator.sequence.Sequence` with full-frame silhouettes and
``truth`` in the result format of DESIGN.md.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import asdict, dataclass

import numpy as np

from .camera import Camera
from .gait import GaitModel, GaitStyle, load_gait, motion_angles, motion_phase
from .joints import JOINT_NAMES, N_JOINTS
from .mocap import Motion
from .render import Renderer
from .sequence import Sequence
from .skeleton import FULL_JOINT_NAMES, BodyShape, GaitAngles, forward_kinematics

__all__ = ["SynthSpec", "place_cameras", "synthesize", "synthesize_recordings", "synthesize_turns", "walk"]

ELEVATION_RANGE = (-20.0, 35.0)
"""Elevations drawn by default: the appearance model's grid (paper: -20 .. +40)."""

_J = {name: i for i, name in enumerate(FULL_JOINT_NAMES)}


@dataclass(frozen=True)
class SynthSpec:
    """What to synthesise. Unset fields are drawn from ``seed``.

    Parameters
    ----------
    n_cameras, n_frames : int
    fps : float
    seed : int
    azimuths, elevations : tuple of float, optional
        One per camera (degrees, DESIGN.md convention).
    shape : BodyShape, optional
    style : GaitStyle, optional
    image_size : (int, int)
        (width, height).
    distance : float, optional
        Camera distance in metres (default: 8–12 m at random, more if the path is long).
    cadence_variation : float
        Relative amplitude of slow changes of the walker's cadence (and speed
        with it: the stride stays), as people speed up and slow down; 0 (the
        default) walks at a constant cadence. Offline synchronisation needs
        them to tell whole gait cycles apart (:mod:`estimator.sync`).
    """

    n_cameras: int = 2
    n_frames: int = 40
    fps: float = 15.0
    seed: int = 0
    azimuths: tuple[float, ...] | None = None
    elevations: tuple[float, ...] | None = None
    shape: BodyShape | None = None
    style: GaitStyle | None = None
    image_size: tuple[int, int] = (640, 480)
    distance: float | None = None
    cadence_variation: float = 0.0

    def __post_init__(self) -> None:
        if self.n_cameras < 1:
            raise ValueError(f"n_cameras must be at least 1, got {self.n_cameras}")
        if self.n_frames < 1:
            raise ValueError(f"n_frames must be at least 1, got {self.n_frames}")
        if self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if not 0.0 <= self.cadence_variation < 0.5:
            raise ValueError(f"cadence_variation must lie in [0, 0.5), got {self.cadence_variation}")
        for name in ("azimuths", "elevations"):
            values = getattr(self, name)
            if values is not None and len(values) != self.n_cameras:
                raise ValueError(f"{name} needs one value per camera ({self.n_cameras}), got {len(values)}")
        if self.elevations is not None and any(not -90 < e < 90 for e in self.elevations):
            raise ValueError(f"elevations must lie in (-90, 90), got {self.elevations}")


def walk(
    phase: np.ndarray, shape: BodyShape, style: GaitStyle, gait: GaitModel, *, time_s: np.ndarray
) -> np.ndarray:
    """World joints (T, 20, 3) of a walker heading along +x, at the origin when t = 0."""
    poses = forward_kinematics(gait.angles(phase, style), shape)
    return poses + np.stack([_speed(shape, style, gait) * time_s, 0 * time_s, 0 * time_s], -1)[:, None]


def _speed(shape: BodyShape, style: GaitStyle, gait: GaitModel) -> float:
    """Walking speed (m/s): two step lengths (ankles apart at heel strike) per cycle."""
    pose = forward_kinematics(gait.angles(np.array([0.0, 0.5]), style), shape)
    step = 0.5 * (pose[0, _J["right_ankle"], 0] - pose[0, _J["left_ankle"], 0]) + 0.5 * (
        pose[1, _J["left_ankle"], 0] - pose[1, _J["right_ankle"], 0]
    )
    return float(2 * step * style.cadence)


def _recorded_walk(motion: Motion, spec: SynthSpec, shape: BodyShape, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """World joints and phases of a recording, resampled to ``spec.fps`` and retargeted."""
    duration = (len(motion) - 1) / motion.fps
    needed = (spec.n_frames - 1) / spec.fps
    if needed > duration:
        raise ValueError(
            f"{motion.source} lasts {duration:.2f} s, {spec.n_frames} frames at {spec.fps} fps need {needed:.2f} s"
        )
    start = rng.uniform(0.0, duration - needed)
    idx = np.round((start + np.arange(spec.n_frames) / spec.fps) * motion.fps).astype(int)
    recorded = motion_angles(motion)
    angles = GaitAngles(**{k: v[idx] for k, v in vars(recorded).items() if k != "extra"})
    pelvis = motion.positions[:, _J["pelvis"], :2]
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pelvis, axis=0), axis=1))])
    x = travel[idx] - travel[idx].mean()
    poses = forward_kinematics(angles, shape)
    poses[..., 0] += x[:, None]
    return poses, motion_phase(motion)[idx]


def _draw(spec: SynthSpec, rng: np.random.Generator
          ) -> tuple[BodyShape, GaitStyle, tuple[float, ...], tuple[float, ...]]:
    """The walker's body and style and the cameras' viewpoints: from ``spec``, else drawn
    from ``rng`` (in this order, which fixes every seed's walk)."""
    shape = spec.shape or BodyShape.random(rng)
    style = spec.style or GaitStyle.random(rng)
    azimuths = spec.azimuths or tuple(float(a) for a in rng.uniform(0.0, 360.0, spec.n_cameras))
    elevations = spec.elevations or tuple(float(e) for e in rng.uniform(*ELEVATION_RANGE, spec.n_cameras))
    return shape, style, azimuths, elevations


def _gait_clock(spec: SynthSpec, style: GaitStyle, phase0: float, time_s: np.ndarray, t0: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """Phase (cycles, wrapped) at ``time_s`` and the time a constant-cadence walker needs to
    cover the same ground (what :func:`walk` places the body by); ``phase0`` at ``t0``.

    With ``spec.cadence_variation`` = a, the cadence is ``cadence * (1 + a * v(t))`` where
    ``v`` is a sum of three sinusoids of periods 2-6 s drawn from the seed (|v| <= 1),
    integrated exactly.
    """
    if spec.cadence_variation == 0.0:
        return (phase0 + style.cadence * (time_s - t0)) % 1.0, time_s
    rng = np.random.default_rng([spec.seed, 0x5C])  # its own stream: the other draws are unchanged
    periods, offsets, weights = rng.uniform(2.0, 6.0, 3), rng.uniform(0.0, 2 * np.pi, 3), rng.dirichlet(np.ones(3))

    def integral(t: np.ndarray) -> np.ndarray:  # of 1 + a v(t) dt
        w = 2 * np.pi / periods
        return t + spec.cadence_variation * np.sum(-weights / w * np.cos(w * t[..., None] + offsets), axis=-1)

    walked = integral(np.asarray(time_s, float)) - integral(np.asarray([t0], float))[0] + t0
    return (phase0 + style.cadence * (walked - t0)) % 1.0, walked


def synthesize_recordings(spec: SynthSpec, clocks: dict[str, np.ndarray], *, gait: GaitModel | None = None
                          ) -> dict[str, Sequence]:
    """One camera's recording per entry of ``clocks``: the same walk seen by unsynchronized cameras.

    ``clocks[name]`` holds the times (s, on the walk's own clock, increasing) at which that
    camera took its frames: its start and frame rate are its own (phones, webcams). The
    cameras (``spec.n_cameras`` = len(clocks); viewpoints, body and style from ``spec``)
    keep the whole walk in frame. Each :class:`Sequence` has one camera, ``fps`` from its
    clock's median interval, and ``truth`` with ``clock`` = ``{"start_s", "fps"}`` and per
    frame ``time_s`` and ``phase``.
    """
    if len(clocks) != spec.n_cameras:
        raise ValueError(f"spec.n_cameras is {spec.n_cameras}, {len(clocks)} clocks given")
    times = {name: np.asarray(t, float) for name, t in clocks.items()}
    if any(t.ndim != 1 or t.size < 2 or np.any(np.diff(t) <= 0) for t in times.values()):
        raise ValueError("each clock needs two or more increasing times")
    rng = np.random.default_rng(spec.seed)
    gait = gait or load_gait()
    shape, style, azimuths, elevations = _draw(spec, rng)
    every = np.unique(np.concatenate(list(times.values())))
    t_mid = 0.5 * (every[0] + every[-1])
    phase, walked = _gait_clock(spec, style, float(rng.uniform()), every - t_mid, 0.0)
    world = walk(phase, shape, style, gait, time_s=walked)
    centroids = world[:, :N_JOINTS].mean(axis=1)
    cameras = place_cameras(azimuths, elevations, centroids=centroids, stature=shape.height,
                            image_size=spec.image_size, distance=spec.distance or float(rng.uniform(8.0, 12.0)))
    out = {}
    with Renderer(shape, image_size=spec.image_size) as renderer:
        for (name, t), cam in zip(times.items(), cameras.values()):
            cam = _keep_in_frame(cam, world, shape.height)
            rows = np.searchsorted(every, t)
            silhouettes = [renderer.render(world[k], cam)[0] for k in rows]
            fps = float(1.0 / np.median(np.diff(t)))
            truth = {"clock": {"start_s": float(t[0]), "fps": fps},
                     "cameras": {name: {"azimuth_deg": cam.azimuth_deg, "elevation_deg": cam.elevation_deg}},
                     "frames": [{"index": i, "time_s": round(float(t[i]), 6), "phase": float(phase[k])}
                                for i, k in enumerate(rows)],
                     "seed": spec.seed}
            out[name] = Sequence(fps=fps, cameras=[name], image_size=spec.image_size,
                                 silhouettes={name: silhouettes}, truth=truth)
    return out


def place_cameras(
    azimuths: tuple[float, ...],
    elevations: tuple[float, ...],
    *,
    centroids: np.ndarray,
    stature: float,
    image_size: tuple[int, int],
    distance: float,
) -> dict[str, Camera]:
    """Fixed cameras ``c0, c1, ...`` aimed at the middle of a walk.

    The focal length puts the body at about 55% of the image height, or smaller
    when needed to keep the whole path (centroids, shape (T, 3)) in the frame;
    the distance grows when the path is long, so the walker never passes the
    camera.
    """
    target = centroids.mean(axis=0)
    path = float(np.ptp(centroids[:, 0]))
    width, height = image_size
    scale = min(0.55 * height / stature, 0.8 * (width / 2) / (path / 2 + 0.35))  # pixels per metre
    distance = max(distance, path / 2 + 3.0)
    return {
        f"c{i}": Camera(az, el, distance=distance, image_size=image_size, focal_px=scale * distance, target=tuple(target))
        for i, (az, el) in enumerate(zip(azimuths, elevations))
    }


def _keep_in_frame(camera: Camera, world: np.ndarray, stature: float) -> Camera:
    """Shorten the focal length until the whole walk (joints plus body radii) is in the image.

    Projections scale linearly about the principal point with the focal length,
    so one factor suffices; head-on and elevated views of a long walk need it.
    """
    uv = camera.project(world.reshape(-1, 3))
    cx, cy = camera.principal_point
    margin = 0.1 * stature * camera.focal_px / camera.distance  # head and foot radii, in pixels
    k = min(
        1.0,
        (cx - 2.0) / (np.abs(uv[:, 0] - cx).max() + margin),
        (cy - 2.0) / (np.abs(uv[:, 1] - cy).max() + margin),
    )
    return dataclasses.replace(camera, focal_px=camera.focal_px * k) if k < 1.0 else camera


def synthesize(
    spec: SynthSpec,
    *,
    gait: GaitModel | None = None,
    motion: Motion | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> Sequence:
    """Render a synthetic sequence with ground truth.

    Parameters
    ----------
    spec : SynthSpec
    gait : GaitModel, optional
        Defaults to the shipped CMU fit.
    motion : Motion, optional
        Drive the body with this recording instead of the gait model.
    progress : callable, optional
        Called as ``progress(done, total)`` after every rendered frame.
    """
    rng = np.random.default_rng(spec.seed)
    gait = gait or load_gait()
    shape, style, azimuths, elevations = _draw(spec, rng)
    time_s = np.arange(spec.n_frames) / spec.fps
    time_s = time_s - time_s.mean()
    if motion is None:
        phase, walked = _gait_clock(spec, style, float(rng.uniform()), time_s, time_s[0])
        world = walk(phase, shape, style, gait, time_s=walked)
    else:
        world, phase = _recorded_walk(motion, spec, shape, rng)
    centroids = world[:, :N_JOINTS].mean(axis=1)
    cameras = place_cameras(
        azimuths,
        elevations,
        centroids=centroids,
        stature=shape.height,
        image_size=spec.image_size,
        distance=spec.distance or float(rng.uniform(8.0, 12.0)),
    )
    cameras = {name: _keep_in_frame(cam, world, shape.height) for name, cam in cameras.items()}
    silhouettes: dict[str, list[np.ndarray | None]] = {c: [] for c in cameras}
    joints2d: dict[str, list[np.ndarray]] = {c: [] for c in cameras}
    total, done = len(cameras) * spec.n_frames, 0
    with Renderer(shape, image_size=spec.image_size) as renderer:
        for name, cam in cameras.items():
            for pose in world:
                sil, j2d = renderer.render(pose, cam)
                silhouettes[name].append(sil)
                joints2d[name].append(j2d)
                done += 1
                if progress is not None:
                    progress(done, total)
    person = world[:, :N_JOINTS] - centroids[:, None]  # heading is +x: person frame = translation
    truth = {
        "joint_names": list(JOINT_NAMES),
        "cameras": {
            name: {
                "azimuth_deg": cam.azimuth_deg,
                "elevation_deg": cam.elevation_deg,
                "distance_m": cam.distance,
                "focal_px": cam.focal_px,
                "position_m": cam.position.tolist(),
            }
            for name, cam in cameras.items()
        },
        "frames": [
            {
                "index": k,
                "phase": float(phase[k]),
                "joints3d": person[k].round(5).tolist(),
                "joints2d": {name: np.round(joints2d[name][k], 3).tolist() for name in cameras},
                "centroid_m": centroids[k].round(5).tolist(),
            }
            for k in range(spec.n_frames)
        ],
        "body": asdict(shape),
        "style": asdict(style),
        "seed": spec.seed,
        "motion": motion.source if motion is not None else None,
        "notes": "viewpoints are from the centroid of the middle of the walk; joints3d in the person frame",
    }
    return Sequence(
        fps=spec.fps,
        cameras=list(cameras),
        image_size=spec.image_size,
        silhouettes=silhouettes,
        truth=truth,
    )


def synthesize_turns(specs: list[SynthSpec], **kwargs) -> Sequence:
    """Walks back to back, one per spec: between them the walker turns, so every viewpoint changes.

    Each stretch is :func:`synthesize` of its spec (``azimuths`` = the cameras'
    viewpoints while the walker keeps that heading; same cameras and image size
    in every spec). ``truth`` holds the frames, renumbered, and ``segments``:
    per stretch its ``first_index``, ``last_index`` and ``cameras``.
    """
    parts = [synthesize(spec, **kwargs) for spec in specs]
    first = parts[0]
    if any(p.cameras != first.cameras or p.image_size != first.image_size for p in parts):
        raise ValueError("every stretch needs the same cameras and image size")
    frames, segments, start = [], [], 0
    for p in parts:
        frames += [dict(f, index=start + k) for k, f in enumerate(p.truth["frames"])]
        segments.append({"first_index": start, "last_index": start + p.n_frames - 1, "cameras": p.truth["cameras"]})
        start += p.n_frames
    return Sequence(fps=first.fps, cameras=list(first.cameras), image_size=first.image_size,
                    silhouettes={c: [s for p in parts for s in p.silhouettes[c]] for c in first.cameras},
                    truth={"joint_names": list(JOINT_NAMES), "frames": frames, "segments": segments,
                           "notes": "walks back to back; viewpoints per segment"})
