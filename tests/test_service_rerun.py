"""Rerun: a service run with a file sink logs every stage of live windows and jobs;
the ``.rrd`` is read back with ``rerun.chunk.RrdReader``."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import zenoh
from rerun.chunk import RrdReader

from capture.wire import Box, SilhouetteMessage, encode, silhouette_key
from capture.zconfig import build_config
from conftest_service import ServerThread, make_settings, sequence_zip, wait_for
from estimator.pipeline import crop_to_box
from estimator.sequence import write_sequence
from estimator.synth import SynthSpec, synthesize
from service.rerun_log import STAGE_PATHS

RIG = "rr"


def _publish_sequence(session: zenoh.Session, seq, fps: float = 60.0) -> None:
    """Publish the sequence's silhouettes as the agents would (index-synchronised), plus
    a camera "blind" that never sees the walker (empty boxes)."""
    cams = [*seq.cameras, "blind"]
    pubs = {c: session.declare_publisher(silhouette_key(RIG, c)) for c in cams}
    epoch = time.time_ns()
    for k in range(seq.n_frames):
        for cam in cams:
            crop = None if cam == "blind" else crop_to_box(seq.silhouettes[cam][k])
            mask, box = (np.zeros((0, 0), np.uint8), Box(0, 0, 0, 0)) if crop is None else \
                (crop[0], Box(*(int(v) for v in crop[1])))
            pubs[cam].put(encode(SilhouetteMessage(
                rig=RIG, camera=cam, frame_index=k, capture_ns=time.time_ns(), box=box,
                image_size=tuple(seq.image_size), epoch_ns=epoch, seq=k, mask=mask, sync="index")))
        time.sleep(1.0 / fps)
    for p in pubs.values():
        p.undeclare()


def test_rrd_holds_every_stage_of_live_windows_and_jobs(tmp_path: Path):
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=40, seed=2, azimuths=(45.0, 135.0), elevations=(10.0, 20.0)))
    write_sequence(tmp_path / "walk", seq)
    rrd = tmp_path / "run.rrd"
    settings = make_settings(tmp_path, live=True, rerun=f"save:{rrd}", window_length=20, window_hop=10)
    with ServerThread(settings) as srv:
        job = srv.client.post("/v1/jobs", files={"files": ("walk.zip", sequence_zip(tmp_path / "walk"))},
                              data={"refine": "true"}).json()
        with zenoh.open(build_config(connect=settings.zenoh_listen)) as session:
            time.sleep(0.3)
            _publish_sequence(session, seq)
        # Priors come from their own loop after a window's estimate (later under load).
        wait_for(lambda: (r := srv.rig(RIG)) and r["windows"]["estimated"] >= 3
                 and r["feedback"]["priors_sent"] > 0, timeout=30, what="three live windows and their priors")
        wait_for(lambda: srv.client.get(f"/v1/jobs/{job['id']}").json()["state"] == "done", timeout=20, what="job")
        latest = srv.client.get(f"/v1/rigs/{RIG}/estimate")
        assert latest.status_code == 200  # strict JSON although one camera saw nothing
        assert latest.json()["cameras"]["blind"]["azimuth_deg"] is None
        assert latest.json()["smoothed"]["blind"]["azimuth_deg"] is None
        time.sleep(0.5)  # the job's stages are logged right after it ends
    assert rrd.stat().st_size > 0
    chunks = list(RrdReader(rrd).stream())
    paths = {c.entity_path.lstrip("/") for c in chunks}
    timelines = set().union(*(c.timeline_names for c in chunks if not c.is_static))
    assert "frame" in timelines
    for prefix in (f"rigs/{RIG}", f"jobs/{job['id']}"):
        for template in STAGE_PATHS:
            for cam in seq.cameras:
                path = f"{prefix}/{template.format(cam=cam)}"
                assert path in paths, f"{path} missing from the recording"
    assert f"rigs/{RIG}/viewpoints/c0/smoothed" in paths
    # The job's person posture and calibrated pinhole cameras (the live path keeps the model's).
    assert f"jobs/{job['id']}/world/person" in paths
    for cam in seq.cameras:
        assert f"jobs/{job['id']}/world/rig/{cam}" in paths
    for cam in seq.cameras:  # §7.1: live priors; the job's raw, prior and refined side by side
        assert f"rigs/{RIG}/feedback/{cam}/prior" in paths
        for layer in ("raw", "prior", "refined"):
            assert f"jobs/{job['id']}/feedback/{cam}/{layer}" in paths
    assert any(p == "" or p == "/" for p in {c.entity_path for c in chunks if c.is_static})  # the AnnotationContext


def test_a_camera_left_out_of_a_live_rig_loses_its_frustum(tmp_path: Path):
    """A live rig recalibrated without a camera clears that camera's pinhole in Rerun (no stale
    frustum from an older calibration); the cameras still in the rig are drawn again, and the
    person's newest posture is drawn at its own frame."""
    from service.rerun_log import RerunLog

    rrd = tmp_path / "rig.rrd"
    log = RerunLog(("save", str(rrd)))
    rig = {"cameras": ["c0", "c1"], "reference": "c0", "rotations": np.stack([np.eye(3)] * 2),
           "centres_m": np.array([[0.0, 0, 0], [4.0, 0, 0]]), "focal_px": np.array([800.0, 800.0]),
           "walker_m": np.array([0.0, 0, 6]), "image_sizes": np.array([[640.0, 480], [640, 480]])}
    log.log_rig("rigs/r", 10, rig, (90.0, 10.0))
    without_c1 = {**rig, "rotations": np.stack([np.eye(3), np.full((3, 3), np.nan)]),
                  "person": (17, np.zeros((13, 3)))}
    log.log_rig("rigs/r", 20, without_c1, (90.0, 10.0))
    log.close()
    fields = {}
    for chunk in RrdReader(rrd).stream():
        fields.setdefault(chunk.entity_path.lstrip("/"), set()).update(chunk.to_record_batch().schema.names)
    assert any(f.startswith("Pinhole:") for f in fields["rigs/r/world/rig/c1"])  # drawn at first
    assert "Clear:is_recursive" in fields["rigs/r/world/rig/c1"]  # then cleared
    assert "Clear:is_recursive" not in fields["rigs/r/world/rig/c0"]
    assert "Points3D:positions" in fields["rigs/r/world/person"]
