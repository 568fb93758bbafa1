"""Batch jobs against a real uvicorn server on 127.0.0.1 with a real SQLite file."""

from __future__ import annotations

import io
import json
import shutil
import zipfile
from pathlib import Path

import pytest

from conftest_service import ServerThread, make_settings, sequence_zip, wait_for
from estimator.sequence import write_sequence
from estimator.synth import SynthSpec, synthesize
from service.jobs import JobStore

TRUTH = (60.0, 150.0)


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    """A synthetic 2-camera, 40-frame sequence folder with truth."""
    path = tmp_path_factory.mktemp("seq") / "walk"
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=40, seed=1, azimuths=TRUTH, elevations=(10.0, 10.0)))
    write_sequence(path, seq)
    return path


@pytest.fixture(scope="module")
def good_zip(seq_dir) -> bytes:
    return sequence_zip(seq_dir)


# Jobs whose posture is not under test take the model's placement (mNBP is most of a job's
# time); test_job_round_trip_and_lifecycle runs the default path.
MODEL = {"posture": "model"}


def _submit(srv: ServerThread, data: bytes, name: str = "walk.zip", form: dict | None = None):
    return srv.client.post("/v1/jobs", files={"files": (name, data, "application/zip")}, data=form)


def _done(srv: ServerThread, job_id: str, timeout: float = 120.0) -> dict:  # a bound, not a speed check
    return wait_for(lambda: (j := srv.client.get(f"/v1/jobs/{job_id}").json())["state"]
                    in ("done", "failed", "cancelled") and j, timeout=timeout, what=f"job {job_id}")


def test_job_round_trip_and_lifecycle(tmp_path, good_zip):
    with ServerThread(make_settings(tmp_path)) as srv:
        r = _submit(srv, good_zip)
        assert r.status_code == 202, r.text
        job = r.json()
        assert job["state"] == "queued" and job["cameras"] == ["c0", "c1"] and job["n_frames"] == 40
        assert r.headers["location"] == f"/v1/jobs/{job['id']}"
        # The API answers while the job runs in the process pool.
        assert srv.client.get("/healthz", timeout=2.0).json()["status"] == "ok"
        done = _done(srv, job["id"])
        assert done["state"] == "done" and done["progress"] == 1.0 and done["attempts"] == 1
        result = srv.client.get(f"/v1/jobs/{job['id']}/result").json()
        assert len(result["joint_names"]) == 13 and len(result["frames"]) == 40
        assert len(result["frames"][0]["joints3d"]) == 13
        # The rig and the person's posture (mNBP postures, then self-calibration, by default).
        assert result["rig"]["reference"] == "c0" and set(result["rig"]["cameras"]) == {"c0", "c1"}
        assert result["rig"]["source"] == "self-calibration", result["notes"]
        assert result["body"]["stature_m"] == 1.75 and "person_joints3d" in result["frames"][0]
        for cam, az in zip(("c0", "c1"), TRUTH):
            assert abs((result["cameras"][cam]["azimuth_deg"] - az + 180) % 360 - 180) < 25
        listed = srv.client.get("/v1/jobs").json()
        assert [j["id"] for j in listed["jobs"]] == [job["id"]] and listed["counts"]["done"] == 1
        assert srv.client.get("/v1/jobs", params={"state": "queued"}).json()["jobs"] == []
        # Ended jobs cannot be cancelled; delete removes the row and the files.
        assert srv.client.post(f"/v1/jobs/{job['id']}/cancel").status_code == 409
        assert (srv.settings.data_dir / job["id"]).exists()
        assert srv.client.delete(f"/v1/jobs/{job['id']}").status_code == 204
        assert srv.client.get(f"/v1/jobs/{job['id']}").status_code == 404
        assert not (srv.settings.data_dir / job["id"]).exists()
        metrics = srv.client.get("/metrics").text
        assert 'posecal_jobs_finished_total{state="done"} 1.0' in metrics
        assert "posecal_job_duration_seconds_count 1.0" in metrics
        # One video per camera: background subtraction in the worker, then the same estimate.
        _check_video_job(srv, tmp_path)


def _videos(tmp: Path, frames: int = 36, pose: Path | None = None) -> list:
    """One small MJPG video per camera of the synthetic walker (12 empty frames first), as upload fields;
    with ``pose``, a detector's keypoints of them there (``write_walk_videos``)."""
    from test_keypoints import write_walk_videos

    return [("files", (p.name, p.read_bytes(), "video/x-msvideo"))
            for p in write_walk_videos(tmp, zip(("c0", "c1"), TRUTH), frames, pose=pose)]


def _check_video_job(srv: ServerThread, tmp_path: Path) -> None:
    r = srv.client.post("/v1/jobs", files=_videos(tmp_path), data={"warmup": "10", "refine": "true"})
    assert r.status_code == 202, r.text
    assert r.json()["kind"] == "videos" and r.json()["cameras"] == ["c0", "c1"]
    done = _done(srv, r.json()["id"])
    assert done["state"] == "done", done
    result = srv.client.get(f"/v1/jobs/{done['id']}/result").json()
    assert len(result["frames"]) == 36 and set(result["cameras"]) == {"c0", "c1"}
    walking = [f for f in result["frames"][12:] if set(f["joints2d"]) == {"c0", "c1"}]
    assert len(walking) >= 20  # the walker was segmented in both videos
    for cam, az in zip(("c0", "c1"), TRUTH):  # 320x240 MJPG segments like 640x480
        assert abs((result["cameras"][cam]["azimuth_deg"] - az + 180) % 360 - 180) < 25, result["cameras"]
    # Silhouettes refined with model feedback (§7.1): background-subtracted again with priors, and
    # (the default feedback=on) the result estimated from them; refine=true serves that same pass.
    assert result["refined"]["silhouettes"] == f"/v1/jobs/{done['id']}/silhouettes"
    assert result["refined"]["priors"] > 0
    assert result["feedback"]["done"] and result["feedback"]["priors"] == result["refined"]["priors"]
    assert result["feedback"]["changed_pixels"] == result["refined"]["changed_pixels"]
    refined = _read_zip_sequence(srv.client.get(result["refined"]["silhouettes"]), tmp_path / "refined")
    assert refined.cameras == ["c0", "c1"] and refined.n_frames == 36
    assert sum(s is not None for s in refined.silhouettes["c0"]) >= 20


def test_a_video_job_takes_a_detectors_keypoints_numbered_by_each_video(tmp_path):
    """Videos with keypoints in each video's own frame numbers and the default sync=auto: the keypoints
    go onto the job's timeline with their video's frames and calibrate its rig (within 3 deg); the
    estimate is not made again from refined silhouettes (the feedback pass serves the postures and the
    rig), but refine=true still gets them."""
    import numpy as np

    from estimator._selfcal_core import geodesic_deg
    from estimator.rig import rotations_from_viewpoints

    files = _videos(tmp_path, 42, pose=tmp_path / "pose")
    with ServerThread(make_settings(tmp_path / "srv")) as srv:
        r = srv.client.post("/v1/jobs", data={"warmup": "10", "refine": "true"}, files=[
            *files, ("keypoints", ("pose.zip", _zip_of(tmp_path / "pose"), "application/zip"))])
        assert r.status_code == 202, r.text
        done = _done(srv, r.json()["id"])
        assert done["state"] == "done", done
        result = srv.client.get(f"/v1/jobs/{done['id']}/result").json()
    assert "sync" in result and any("detector's keypoints" in n for n in result["notes"]), result["notes"]
    assert "feedback" not in result  # the keypoints give the rig and the postures: no feedback pass
    # refine=true without a feedback pass: the videos are segmented a second time for it alone
    assert result["refined"]["priors"] > 0 and result["refined"]["silhouettes"].endswith("/silhouettes")
    assert result["rig"]["source"] == "self-calibration"
    truth = rotations_from_viewpoints([(az, 10.0) for az in TRUTH])
    assert geodesic_deg(np.array(result["rig"]["cameras"]["c1"]["rotation"]), truth[1] @ truth[0].T) < 3.0


def _read_zip_sequence(response, folder: Path):
    from estimator.sequence import read_sequence

    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/zip"
    zipfile.ZipFile(io.BytesIO(response.content)).extractall(folder)
    return read_sequence(folder)


def test_refined_silhouettes_of_a_sequence_job(tmp_path, seq_dir, good_zip):
    with ServerThread(make_settings(tmp_path)) as srv:
        plain = _submit(srv, good_zip, form=MODEL).json()
        refined = _submit(srv, good_zip, form={"refine": "true", **MODEL}).json()
        for job in (plain, refined):
            assert _done(srv, job["id"])["state"] == "done"
        assert srv.client.get(f"/v1/jobs/{plain['id']}/silhouettes").status_code == 404
        assert "refined" not in srv.client.get(f"/v1/jobs/{plain['id']}/result").json()
        result = srv.client.get(f"/v1/jobs/{refined['id']}/result").json()
        seq = _read_zip_sequence(srv.client.get(f"/v1/jobs/{refined['id']}/silhouettes"), tmp_path / "out")
    from estimator.sequence import read_sequence

    original = read_sequence(seq_dir)
    assert seq.cameras == original.cameras and seq.n_frames == original.n_frames
    assert result["refined"]["priors"] == 2 * original.n_frames
    changed = sum(int(((a > 0) != (b > 0)).sum()) for c in seq.cameras
                  for a, b in zip(seq.silhouettes[c], original.silhouettes[c]) if a is not None)
    assert changed == result["refined"]["changed_pixels"] > 0  # measured: a few dozen pixels


def test_a_job_reports_one_segment_per_heading(tmp_path, turn_sequence):
    from conftest import TURN_AFTER, TURN_BEFORE

    write_sequence(tmp_path / "turn", turn_sequence)
    with ServerThread(make_settings(tmp_path, change_windows=2)) as srv:
        job = _submit(srv, sequence_zip(tmp_path / "turn"), form=MODEL).json()
        assert _done(srv, job["id"])["state"] == "done"
        result = srv.client.get(f"/v1/jobs/{job['id']}/result").json()
    assert len(result["frames"]) == 80 and [s["first_index"] for s in result["segments"]][0] == 0
    assert len(result["segments"]) == 2 and len(result["windows"]) == 7
    for seg, truth in zip(result["segments"], (TURN_BEFORE, TURN_AFTER)):
        for cam, az in zip(("c0", "c1"), truth):
            assert abs((seg["cameras"][cam]["azimuth_deg"] - az + 180) % 360 - 180) < 25


def test_silhouettes_of_an_unfinished_job_are_409(tmp_path, good_zip):
    with ServerThread(make_settings(tmp_path, job_workers=0)) as srv:  # jobs stay queued
        job = srv.client.post("/v1/jobs", files={"files": ("walk.zip", good_zip, "application/zip")},
                              data={"refine": "true"}).json()
        r = srv.client.get(f"/v1/jobs/{job['id']}/silhouettes")
        assert r.status_code == 409 and "queued" in r.json()["detail"]
        assert srv.client.get("/v1/jobs/nope/silhouettes").status_code == 404


def test_restart_runs_queued_and_requeues_interrupted_jobs(tmp_path, good_zip):
    # First server: no job workers, so submitted jobs stay queued; cancel one.
    with ServerThread(make_settings(tmp_path, job_workers=0)) as srv:
        ids = [_submit(srv, good_zip, form=MODEL).json()["id"] for _ in range(2)]
        cancelled = _submit(srv, good_zip).json()["id"]
        assert srv.client.post(f"/v1/jobs/{cancelled}/cancel").json()["state"] == "cancelled"
        assert srv.client.get(f"/v1/jobs/{cancelled}/result").status_code == 409
    # Simulate a crash mid-job: the first job is left "running" in the database.
    store = JobStore(make_settings(tmp_path).db_url)
    assert store.claim_next().id == ids[0]
    store.close()
    with ServerThread(make_settings(tmp_path)) as srv:
        for job_id in ids:
            done = _done(srv, job_id)
            assert done["state"] == "done", done
        assert _done(srv, ids[0])["attempts"] == 2  # re-queued after the "crash"
        assert srv.client.get(f"/v1/jobs/{cancelled}").json()["state"] == "cancelled"
        assert len(srv.client.get(f"/v1/jobs/{ids[1]}/result").json()["frames"]) == 40


def _zip(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _zip_of(folder: Path) -> bytes:
    return sequence_zip(folder)


def test_bad_uploads_get_clear_4xx_and_disturb_nothing(tmp_path, seq_dir, good_zip):
    settings = make_settings(tmp_path, upload_limit_mb=1.0)
    with ServerThread(settings) as srv:
        good = _submit(srv, good_zip).json()["id"]

        big = srv.client.post("/v1/jobs", files={"files": ("walk.zip", b"\0" * (2 << 20), "application/zip")})
        assert big.status_code == 413 and "limit" in big.json()["detail"]

        r = _submit(srv, b"PK\x03\x04 definitely not a zip")
        assert r.status_code == 400 and "zip" in r.json()["detail"]

        r = _submit(srv, _zip({}))
        assert r.status_code in (400, 422)

        r = _submit(srv, _zip({"readme.txt": b"hello"}))
        assert r.status_code == 422 and "rig.json" in r.json()["detail"]

        broken = tmp_path / "broken" / "walk"
        shutil.copytree(seq_dir, broken)
        (broken / "c1" / "000003.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")
        r = _submit(srv, _zip_of(broken))
        assert r.status_code == 422 and "000003.png" in r.json()["detail"], r.text

        mismatched = tmp_path / "mismatched" / "walk"
        shutil.copytree(seq_dir, mismatched)
        rig = json.loads((mismatched / "rig.json").read_text())
        rig["cameras"] = ["c0", "c1", "c2"]
        (mismatched / "rig.json").write_text(json.dumps(rig))
        r = _submit(srv, _zip_of(mismatched))
        assert r.status_code == 422 and "c2" in r.json()["detail"]

        evil = _zip({"../../escape.txt": b"x", "walk/rig.json": b"{}"})
        r = _submit(srv, evil)
        assert r.status_code == 400 and "outside" in r.json()["detail"]

        r = srv.client.post("/v1/jobs", files={"files": ("c0.mp4", b"not a video", "video/mp4")})
        assert r.status_code == 422 and "c0.mp4" in r.json()["detail"]

        r = srv.client.post("/v1/jobs", files={"files": ("notes.txt", b"hi", "text/plain")})
        assert r.status_code == 415

        assert srv.client.post("/v1/jobs").status_code == 422  # no files at all
        r = srv.client.post("/v1/jobs", files={"files": ("walk.zip", good_zip, "application/zip")},
                            data={"height_m": "17.5"})
        assert r.status_code == 422 and "height_m" in r.text
        r = srv.client.post("/v1/jobs", files={"files": ("walk.zip", good_zip, "application/zip")},
                            data={"feedback": "maybe"})
        assert r.status_code == 422 and "feedback" in r.text
        for path in ("/v1/jobs/nope", "/v1/jobs/nope/result"):
            assert srv.client.get(path).status_code == 404
        assert srv.client.post("/v1/jobs/nope/cancel").status_code == 404
        assert srv.client.delete("/v1/jobs/nope").status_code == 404

        # Nothing else was disturbed: the good job finishes; rejected uploads left no rows or files.
        assert _done(srv, good)["state"] == "done"
        assert [j["id"] for j in srv.client.get("/v1/jobs").json()["jobs"]] == [good]
        assert [p.name for p in settings.data_dir.iterdir()] == [good]
        metrics = srv.client.get("/metrics").text
        assert 'posecal_uploads_rejected_total{status="422"}' in metrics


def test_a_dead_worker_process_is_replaced(tmp_path, good_zip):
    """A job worker killed (out of memory, a native crash) fails its job; the next job runs
    in a fresh pool."""
    import os
    import signal

    with ServerThread(make_settings(tmp_path)) as srv:
        pool = srv.runtime.job_pool
        first = _done(srv, _submit(srv, good_zip, form=MODEL).json()["id"])
        assert first["state"] == "done"
        for pid in pool.pids:
            os.kill(pid, signal.SIGKILL)
        wait_for(lambda: not any(_alive(p) for p in pool.pids), timeout=10, what="workers gone")
        again = _done(srv, _submit(srv, good_zip, form=MODEL).json()["id"])
        assert again["state"] == "done", again
        assert pool.restarts == 1


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split(")")[-1].split()[0] != "Z"  # a zombie is dead too
    except FileNotFoundError:
        return False


def test_a_job_calibrates_the_rig_from_uploaded_keypoints(tmp_path):
    """``keypoints=`` beside the recording: a zip of OpenPose folders (a detector's errors on the renders'
    joints) calibrates the job's rig in place of the mNBP postures, within 2 deg of the truth; keypoints
    that do not fit the recording are refused with the reason, and the next job goes on."""
    import numpy as np

    from estimator._selfcal_core import geodesic_deg
    from estimator.damage import detector_keypoints
    from estimator.rig import rotations_from_viewpoints
    from test_keypoints import write_openpose

    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=8, azimuths=(40.0, 110.0, 300.0),
                               elevations=(5.0, 15.0, 10.0), image_size=(320, 240)))
    write_sequence(tmp_path / "walk", seq)
    joints = np.array([[f["joints2d"][c] for f in seq.truth["frames"]] for c in seq.cameras])
    write_openpose(tmp_path / "pose", seq.cameras, detector_keypoints(joints, np.random.default_rng(2)))
    write_openpose(tmp_path / "other" / "pose", ["a", "b", "c"], joints)  # cameras of another rig

    def submit(srv, keypoints: Path | None, **form):
        files = {"files": ("walk.zip", sequence_zip(tmp_path / "walk"), "application/zip")}
        if keypoints is not None:
            files["keypoints"] = ("pose.zip", _zip_of(keypoints), "application/zip")
        return srv.client.post("/v1/jobs", files=files, data=form)

    with ServerThread(make_settings(tmp_path / "srv")) as srv:
        r = submit(srv, tmp_path / "pose", height_m="1.8")
        assert r.status_code == 202, r.text
        bad = submit(srv, tmp_path / "other")
        assert bad.status_code == 422 and "keypoints" in bad.json()["detail"] and "match fewer than two" in \
            bad.json()["detail"], bad.text
        assert str(srv.settings.data_dir) not in bad.json()["detail"]  # no server paths in the reason
        junk = srv.client.post("/v1/jobs", files={"files": ("walk.zip", sequence_zip(tmp_path / "walk")),
                                                  "keypoints": ("pose.zip", b"not a zip")})
        assert junk.status_code == 400 and "keypoints" in junk.json()["detail"]
        # files that lie: a frame number beyond any integer type (left out: it is not in the recording),
        # a file nested too deeply (refused with a reason, not a 500)
        shutil.copytree(tmp_path / "pose", tmp_path / "huge" / "pose")
        (tmp_path / "huge" / "pose" / "c0_json" / f"c0_{'9' * 20}_keypoints.json").write_text(
            (tmp_path / "pose" / "c0_json" / "c0_000000000000_keypoints.json").read_text())
        assert submit(srv, tmp_path / "huge").status_code == 202
        shutil.copytree(tmp_path / "pose", tmp_path / "deep" / "pose")
        (tmp_path / "deep" / "pose" / "c1_json" / "c1_000000000003_keypoints.json").write_text("[" * 100_000)
        deep = submit(srv, tmp_path / "deep")
        assert deep.status_code == 422 and "keypoints" in deep.json()["detail"], deep.text
        done = _done(srv, r.json()["id"])
        assert done["state"] == "done", done
        result = srv.client.get(f"/v1/jobs/{done['id']}/result").json()
        assert any("detector's keypoints" in n for n in result["notes"]), result["notes"]
        rig = result["rig"]
        assert rig["source"] == "self-calibration" and result["body"]["stature_m"] == 1.8
        truth = rotations_from_viewpoints([(seq.truth["cameras"][c]["azimuth_deg"],
                                            seq.truth["cameras"][c]["elevation_deg"]) for c in seq.cameras])
        errors = [geodesic_deg(np.array(rig["cameras"][c]["rotation"]), truth[k])
                  for k, c in enumerate(seq.cameras) if k]
        assert max(errors) < 2.0, errors
        assert srv.client.get("/v1/jobs").json()["counts"]["done"] >= 1
        assert len(srv.client.get("/v1/jobs").json()["jobs"]) == 2  # the refused uploads left no job
        assert sorted(p.name for p in srv.settings.data_dir.iterdir()) == sorted(
            j["id"] for j in srv.client.get("/v1/jobs").json()["jobs"])  # nor files
