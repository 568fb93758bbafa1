"""Every Rerun call of the service: one :class:`RerunLog` (one RecordingStream) per run.

Laid out like Rerun's human_pose_tracking example: the skeleton's
AnnotationContext (keypoint names and bones) is logged once, statically; every
per-frame item sets the ``frame`` timeline, then logs. Entity paths follow
coordinate spaces, under a prefix per rig (``rigs/<rig>``) or job
(``jobs/<id>``)::

    <P>/inputs/<cam>                      input silhouette crop (SegmentationImage)
    <P>/registration/<cam>/silhouette     registered silhouette (canvas)
    <P>/registration/<cam>/cluster_mean   mean of the matched cluster, beside it
    <P>/viewpoints/<cam>/cloud            member viewpoints of the matched clusters (az, el)
    <P>/viewpoints/<cam>/ellipse          the fitted 2-sigma ellipse
    <P>/viewpoints/<cam>/smoothed         the viewpoint smoothed across windows (live)
    <P>/phase/observed/<cam>              per-camera phase observation (scalar)
    <P>/phase/hmm                         the HMM (Viterbi) path (scalar)
    <P>/world/skeleton                    3D joints (person frame), keypoints + bones
    <P>/world/person                      the person's posture (self-calibrated), 1 m to the left (jobs: every
                                          frame; live rigs: the newest frame of each calibration)
    <P>/world/cameras/<cam>               estimated camera: Transform3D + Pinhole
    <P>/world/cameras/<cam>/box           silhouette box in that camera's image
    <P>/world/cameras/<cam>/joints        2D joints in that camera's image
    <P>/world/rig/<cam>                   the calibrated pinhole camera (jobs; live rigs when their
                                          calibration updates): pose, focal length
    <P>/feedback/<cam>/prior              §7.1 prior sent for a frame (live: predicted ahead)
    <P>/feedback/<cam>/raw                jobs with refine: the raw silhouette, ...
    <P>/feedback/<cam>/refined            ... and the refined one, cut to the same box as the prior

A capture agent run with ``posecal capture --rerun`` logs its camera's view
(:meth:`RerunLog.log_capture`, every ``rerun_every``-th frame) side by side::

    capture/<cam>/raw                     the frame (BGR)
    capture/<cam>/background              the segmenter's background model
    capture/<cam>/silhouette              the silhouette it published (full frame, 0/255)

Fed only by plain arrays (:class:`service.worker.StageBundle`, the agent's frames).
"""

from __future__ import annotations

import logging
import threading

import numpy as np
import rerun as rr

from estimator.camera import viewpoint_direction, world_to_camera_rotation
from estimator.joints import BONES, JOINT_NAMES
from estimator.viewpoint import azimuth_difference_deg

from .worker import StageBundle

__all__ = ["CAPTURE_PATHS", "RerunLog", "STAGE_PATHS"]

log = logging.getLogger(__name__)

TIMELINE = "frame"
CAMERA_DISTANCE_M = 4.0  # where viewpoint cameras are drawn: scaled orthography fixes no distance
PERSON_OFFSET_M = np.array([0.0, 1.0, 0.0])  # the person's posture beside the model's skeleton
STAGE_PATHS = ("inputs/{cam}", "registration/{cam}/silhouette", "registration/{cam}/cluster_mean",
               "viewpoints/{cam}/cloud", "viewpoints/{cam}/ellipse", "phase/observed/{cam}",
               "phase/hmm", "world/skeleton", "world/cameras/{cam}", "world/cameras/{cam}/joints")
"""Entity paths (under a prefix) that every estimated window writes."""
CAPTURE_PATHS = ("capture/{cam}/raw", "capture/{cam}/background", "capture/{cam}/silhouette")
"""Entity paths of a capture agent's view (:meth:`RerunLog.log_capture`)."""

_WALKER = 0


class RerunLog:
    """One recording of the service run, streamed to one sink.

    Parameters
    ----------
    sink : ("save", path) | ("serve", port) | ("connect", url)
        A ``.rrd`` file, a gRPC server on 127.0.0.1 that viewers connect to, or
        a viewer (gRPC server) to connect to.
    """

    def __init__(self, sink: tuple[str, str | int], *, recording_id: str | None = None) -> None:
        kind, target = sink
        self.stream = rr.RecordingStream("posecal", recording_id=recording_id)
        self.uri: str | None = None
        if kind == "save":
            self.stream.set_sinks(rr.FileSink(str(target)))
        elif kind == "serve":
            server = rr.GrpcServerSink(bind_ip="127.0.0.1", port=int(target))
            self.uri = server.uri
            self.stream.set_sinks(server)
        elif kind == "connect":
            self.stream.set_sinks(rr.GrpcSink(str(target)))
        else:
            raise ValueError(f"unknown rerun sink {kind!r}")
        self._lock = threading.Lock()
        self._prefixes: set[str] = set()
        self.stream.log("/", rr.AnnotationContext([rr.ClassDescription(
            info=rr.AnnotationInfo(id=_WALKER, label="walker", color=(90, 200, 255)),
            keypoint_annotations=[rr.AnnotationInfo(id=i, label=n) for i, n in enumerate(JOINT_NAMES)],
            keypoint_connections=list(BONES))]), static=True)

    def _setup(self, prefix: str) -> None:
        if prefix not in self._prefixes:
            self.stream.log(f"{prefix}/world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
            self._prefixes.add(prefix)

    def log_window(self, prefix: str, b: StageBundle) -> None:
        """Log every stage of one estimate; per-frame items from ``b.extra['from_frame']`` on."""
        with self._lock:
            self._setup(prefix)
            self._log_window(prefix, b)

    def _log_window(self, p: str, b: StageBundle) -> None:
        s = self.stream
        first = int(b.extra.get("from_frame", 0))
        for t in range(first, len(b.indices)):
            s.set_time(TIMELINE, sequence=int(b.indices[t]))
            for cam in b.crops:
                crop = b.crops[cam][t]
                if crop is not None:
                    s.log(f"{p}/inputs/{cam}", rr.SegmentationImage((crop > 0).astype(np.uint8)))
                reg = b.registered[cam][t]
                if reg is not None:
                    s.log(f"{p}/registration/{cam}/silhouette", rr.SegmentationImage((reg > 0).astype(np.uint8)))
                    label = int(b.labels[cam][t])
                    if label in b.means:
                        s.log(f"{p}/registration/{cam}/cluster_mean", rr.Image(b.means[label]))
                obs = b.observations[cam][t]
                if np.isfinite(obs):
                    s.log(f"{p}/phase/observed/{cam}", rr.Scalars(float(obs)))
                box = b.boxes[cam][t]
                if np.all(np.isfinite(box)):
                    s.log(f"{p}/world/cameras/{cam}/box", rr.Boxes2D(mins=box[:2], sizes=box[2:]))
                j2d = b.joints2d[cam][t]
                if np.all(np.isfinite(j2d)):
                    s.log(f"{p}/world/cameras/{cam}/joints", rr.Points2D(
                        j2d, class_ids=_WALKER, keypoint_ids=np.arange(len(JOINT_NAMES)), radii=2.0))
            s.log(f"{p}/phase/hmm", rr.Scalars(float(b.phase[t])))
            s.log(f"{p}/world/skeleton", rr.Points3D(
                b.joints3d[t], class_ids=_WALKER, keypoint_ids=np.arange(len(JOINT_NAMES)), radii=0.03))
            person = b.extra.get("person")
            if person is not None:
                self._log_person(p, person[t])
            for cam, views in b.extra.get("feedback", {}).items():
                if t < len(views) and views[t] is not None:
                    for name, img in zip(("raw", "prior", "refined"), views[t]):
                        s.log(f"{p}/feedback/{cam}/{name}", rr.Image(img))
        # Per-window items at the window's last frame.
        s.set_time(TIMELINE, sequence=int(b.indices[-1]))
        for cam, vp in b.viewpoints.items():
            az, el = vp["azimuth_deg"], vp["elevation_deg"]
            if not (np.isfinite(az) and np.isfinite(el)):
                continue
            cloud = b.clouds.get(cam)
            if cloud is not None and len(cloud):
                unwrapped = np.stack([az + azimuth_difference_deg(cloud[:, 0], az), cloud[:, 1]], -1)
                s.log(f"{p}/viewpoints/{cam}/cloud", rr.Points2D(unwrapped, radii=0.6))
            s.log(f"{p}/viewpoints/{cam}/ellipse", rr.LineStrips2D([_ellipse(az, el, vp["covariance"])]))
            self._log_camera(p, cam, az, el, b.image_size.get(cam, (640, 480)))
        if "rig" in b.extra:
            ref = b.viewpoints.get(b.extra["rig"]["reference"], {})
            self._log_rig(p, b.extra["rig"], ref.get("azimuth_deg", np.nan), ref.get("elevation_deg", np.nan))

    def _log_camera(self, p: str, cam: str, az: float, el: float, size: tuple[int, int]) -> None:
        R = world_to_camera_rotation(az, el)  # rows: u, v, viewing direction = camera RDF axes
        self.stream.log(f"{p}/world/cameras/{cam}", rr.Transform3D(
            translation=CAMERA_DISTANCE_M * viewpoint_direction(az, el), mat3x3=R.T))
        self.stream.log(f"{p}/world/cameras/{cam}", rr.Pinhole(
            resolution=[int(size[0]), int(size[1])], focal_length=1.2 * float(size[0]),
            camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.8))

    def log_rig(self, prefix: str, index: int, rig: dict, reference_viewpoint: tuple[float, float]) -> None:
        """A live rig's calibrated pinhole cameras (``worker.rig_arrays``) at frame ``index``, placed
        through the reference camera's latest viewpoint ``(azimuth, elevation)``, and the person's
        newest posture (``rig["person"]``: frame index, joints) at its own frame."""
        with self._lock:
            self._setup(prefix)
            self.stream.set_time(TIMELINE, sequence=int(index))
            self._log_rig(prefix, rig, *reference_viewpoint)
            if rig.get("person") is not None:
                frame, joints = rig["person"]
                self.stream.set_time(TIMELINE, sequence=int(frame))
                self._log_person(prefix, np.asarray(joints, float))

    def _log_person(self, p: str, joints: np.ndarray) -> None:
        """The person's posture (13, 3), its joints that are known, 1 m beside the model's skeleton."""
        ok = np.isfinite(joints).all(axis=1)
        if ok.any():
            self.stream.log(f"{p}/world/person", rr.Points3D(
                joints[ok] + PERSON_OFFSET_M, class_ids=_WALKER, keypoint_ids=np.flatnonzero(ok), radii=0.03))

    def _log_rig(self, p: str, rig: dict, az: float, el: float) -> None:
        """The calibrated pinhole cameras, placed in the person frame through the reference
        camera's viewpoint (the rig itself is relative to that camera), the walker at the origin."""
        if not (np.isfinite(az) and np.isfinite(el)):
            return
        r0 = world_to_camera_rotation(az, el)  # person frame -> reference camera
        for k, cam in enumerate(rig["cameras"]):
            if not (np.all(np.isfinite(rig["rotations"][k])) and np.isfinite(rig["focal_px"][k])):
                # left out of the pinhole rig (no viewpoint, or its rotation from the viewpoint only): no stale frustum
                self.stream.log(f"{p}/world/rig/{cam}", rr.Clear(recursive=True))
                continue
            r = rig["rotations"][k] @ r0
            size = rig["image_sizes"][k] if np.all(np.isfinite(rig["image_sizes"][k])) else (640, 480)
            self.stream.log(f"{p}/world/rig/{cam}", rr.Transform3D(
                translation=r0.T @ (rig["centres_m"][k] - rig["walker_m"]), mat3x3=r.T))
            self.stream.log(f"{p}/world/rig/{cam}", rr.Pinhole(
                resolution=[int(size[0]), int(size[1])], focal_length=float(rig["focal_px"][k]),
                camera_xyz=rr.ViewCoordinates.RDF, image_plane_distance=0.8))

    def log_smoothed(self, prefix: str, index: int, smoothed: dict[str, dict]) -> None:
        """The live viewpoint smoothed across windows, per camera."""
        with self._lock:
            self.stream.set_time(TIMELINE, sequence=int(index))
            for cam, sm in smoothed.items():
                if sm.get("azimuth_deg") is None:
                    continue
                self.stream.log(f"{prefix}/viewpoints/{cam}/smoothed", rr.Points2D(
                    [[sm["azimuth_deg"], sm["elevation_deg"]]], radii=3.0, colors=(255, 80, 80)))

    def log_priors(self, prefix: str, priors: dict[str, list[tuple[int, tuple, np.ndarray]]]) -> None:
        """Live §7.1 priors, each at the frame it was predicted for (``inputs/<cam>`` then
        shows the silhouette the agent made with it)."""
        with self._lock:
            for cam, items in priors.items():
                for index, _box, mask in items:
                    self.stream.set_time(TIMELINE, sequence=int(index))
                    self.stream.log(f"{prefix}/feedback/{cam}/prior", rr.Image(mask))

    def log_capture(self, camera: str, index: int, frame: np.ndarray,
                    background: np.ndarray | None, silhouette: np.ndarray) -> None:
        """A capture agent's view of frame ``index``: the BGR frame, the background
        model (BGR; None = not known yet) and the full-frame silhouette (0/255)."""
        raw, bg, sil = (p.format(cam=camera) for p in CAPTURE_PATHS)
        with self._lock:
            self.stream.set_time(TIMELINE, sequence=int(index))
            self.stream.log(raw, rr.Image(frame, color_model="BGR"))
            if background is not None:
                self.stream.log(bg, rr.Image(background, color_model="BGR"))
            self.stream.log(sil, rr.Image(silhouette))

    def close(self) -> None:
        with self._lock:
            try:
                self.stream.flush(timeout_sec=10.0)
            finally:
                self.stream.disconnect()


def _ellipse(az: float, el: float, cov: np.ndarray, n: int = 48, k: float = 2.0) -> np.ndarray:
    """Points of the k-sigma ellipse of ``cov`` around (az, el): (n + 1, 2)."""
    cov = np.asarray(cov, float)
    if cov.shape != (2, 2) or not np.all(np.isfinite(cov)):
        cov = np.eye(2)
    w, v = np.linalg.eigh((cov + cov.T) / 2)
    a = np.linspace(0, 2 * np.pi, n + 1)
    circle = np.stack([np.cos(a), np.sin(a)], -1)
    return np.array([az, el]) + k * (circle * np.sqrt(np.maximum(w, 1e-6))) @ v.T
