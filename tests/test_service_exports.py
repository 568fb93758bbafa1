"""The exports over REST (issue 18): ``GET /v1/jobs/{id}/result?format=`` and
``GET /v1/rigs/{rig}/calibration?format=``, against a real uvicorn server on 127.0.0.1."""

from __future__ import annotations

import csv
import io

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from conftest_service import ServerThread, make_settings, sequence_zip, wait_for, write_walk
from estimator.joints import JOINT_NAMES, N_JOINTS
from estimator.mocap import bvh_positions
from estimator.rig import Rig
from service.jobs import JobStore
from test_exports import _anipose_load

TEXT = {"trc": "text/plain", "bvh": "text/plain", "csv": "text/csv", "toml": "application/toml",
        "yaml": "application/yaml"}


@pytest.fixture(scope="module")
def walk_zip(tmp_path_factory) -> bytes:
    return sequence_zip(write_walk(tmp_path_factory.mktemp("seq") / "walk", n_frames=40, seed=1))


def _job(srv: ServerThread, data: bytes, **form) -> str:
    r = srv.client.post("/v1/jobs", files={"files": ("walk.zip", data, "application/zip")}, data=form)
    assert r.status_code == 202, r.text
    job_id = r.json()["id"]
    done = wait_for(lambda: (j := srv.client.get(f"/v1/jobs/{job_id}").json())["state"]
                    in ("done", "failed", "cancelled") and j, timeout=60, what=f"job {job_id}")
    assert done["state"] == "done", done
    return job_id


def _get(srv: ServerThread, url: str, fmt: str, status: int = 200):
    r = srv.client.get(url, params={"format": fmt})
    assert r.status_code == status, (fmt, r.text)
    if status == 200:
        assert r.headers["content-type"].split(";")[0] == TEXT[fmt]
        assert r.headers["content-disposition"].endswith(f'.{fmt}"')
    return r


def _yaml_cameras(text: str) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray]]:
    fs = cv2.FileStorage(text, cv2.FILE_STORAGE_READ | cv2.FILE_STORAGE_MEMORY)
    node = fs.getNode("cameras")
    return [(node.at(i).getNode("name").string(), node.at(i).getNode("K").mat(), node.at(i).getNode("R").mat(),
             node.at(i).getNode("t").mat()) for i in range(node.size())]


def test_a_job_result_in_every_format(tmp_path, walk_zip):
    with ServerThread(make_settings(tmp_path)) as srv:
        job = _job(srv, walk_zip)
        url = f"/v1/jobs/{job}/result"
        result = srv.client.get(url).json()  # json, the default
        texts = {fmt: _get(srv, url, fmt).text for fmt in ("trc", "bvh", "csv")}
        metric = all(c.get("focal_px") is not None for c in result["rig"]["cameras"].values())
        calib = {fmt: _get(srv, url, fmt, 200 if metric else 400) for fmt in ("toml", "yaml")}
        assert srv.client.get(url, params={"format": "c3d"}).status_code == 422
        other = _job(srv, walk_zip, posture="model")  # a rig from the viewpoints: no metric cameras
        r = _get(srv, f"/v1/jobs/{other}/result", "toml", 400)
        assert "no metric cameras" in r.json()["detail"] and "'viewpoints'" in r.json()["detail"]
        assert _get(srv, f"/v1/jobs/{other}/result", "trc").text.count("\n") == 5 + 40  # the model's joints
        assert srv.client.get("/v1/jobs/nope/result", params={"format": "trc"}).status_code == 404
    # The joints: the person's measured posture (person_joints3d), person frame, z up, metres.
    rows = list(csv.reader(io.StringIO(texts["csv"])))
    assert len(rows) == 41 and rows[1][0] == str(result["frames"][0]["index"])
    joints = np.array([[float(v) if v else np.nan for v in r[2:]] for r in rows[1:]]).reshape(40, N_JOINTS, 3)
    person = np.array([[p if p is not None else [np.nan] * 3 for p in f["person_joints3d"]] for f in result["frames"]])
    np.testing.assert_allclose(joints, person, atol=1e-6)
    assert texts["trc"].startswith(f"PathFileType\t4\t(X/Y/Z)\t{job}.trc\n")
    path = tmp_path / "job.bvh"
    path.write_text(texts["bvh"])
    hips = bvh_positions(path)[0]["Hips"][:, [2, 0, 1]]  # the root: the hips' midpoint, back to z up
    mid = person[:, [JOINT_NAMES.index("left_hip"), JOINT_NAMES.index("right_hip")]].mean(axis=1)
    seen = np.isfinite(mid).all(axis=1)
    np.testing.assert_allclose(hips[seen], mid[seen], atol=1e-5)
    if metric:  # the rig's cameras, in the reference camera's frame
        cams = {c["name"]: c for c in _anipose_load(calib["toml"].text)}
        for name, cam in result["rig"]["cameras"].items():
            assert cams[name]["matrix"][0, 0] == pytest.approx(cam["focal_px"])
            assert list(cams[name]["size"]) == cam["image_size"]
        assert [c[0] for c in _yaml_cameras(calib["yaml"].text)] == list(result["rig"]["cameras"])
    else:
        assert "no metric cameras" in calib["toml"].json()["detail"]


def _metric_rig() -> dict:
    """A pinhole rig as Rig.to_dict writes it (the reference and a camera 4 m to its side, turned 60 deg)."""
    rot = np.stack([np.eye(3), Rotation.from_euler("y", -60, degrees=True).as_matrix()])
    rig = Rig(("c0", "c1"), rot, np.array([1.0, 0.9]), "self-calibration", focal_px=np.array([800.0, 900.0]),
              centres_m=np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 1.5]]), image_sizes=np.array([[640, 480], [1280, 720]]))
    return rig.to_dict()


def test_a_stored_result_reads_back_in_the_peers_formats(tmp_path):
    """A finished job's result with a metric rig (stored directly): the TOML as aniposelib reads it and the
    OpenCV YAML hold the rig's cameras, world = the reference camera's frame."""
    settings = make_settings(tmp_path, job_workers=0)
    with ServerThread(settings) as srv:
        store = JobStore(settings.db_url)
        job = store.create(kind="sequence", input_dir=str(tmp_path)).id
        assert store.claim_next().id == job
        frames = [{"index": k, "joints3d": np.zeros((N_JOINTS, 3)).tolist()} for k in range(3)]
        store.finish(job, {"frames": frames, "fps": 25.0, "rig": _metric_rig(), "body": {"stature_m": 1.6}})
        store.close()
        toml = _get(srv, f"/v1/jobs/{job}/result", "toml").text
        yaml = _get(srv, f"/v1/jobs/{job}/result", "yaml").text
        bvh = _get(srv, f"/v1/jobs/{job}/result", "bvh", 400)  # every joint at one point: no bone to aim
        assert "coincident joints" in bvh.json()["detail"]
    cams = {c["name"]: c for c in _anipose_load(toml)}
    c1 = cams["c1"]
    assert c1["size"] == (1280, 720) and np.allclose(c1["matrix"], [[900, 0, 640], [0, 900, 360], [0, 0, 1]])
    r1 = cv2.Rodrigues(c1["rvec"])[0]
    np.testing.assert_allclose(-r1.T @ c1["tvec"], [4.0, 0.0, 1.5], atol=1e-9)  # the camera centre
    assert np.allclose(cams["c0"]["rvec"], 0) and np.allclose(cams["c0"]["tvec"], 0)
    (name0, k0, r0, t0), (name1, k1, rr1, t1) = _yaml_cameras(yaml)
    assert (name0, name1) == ("c0", "c1") and np.allclose(rr1, r1) and np.allclose(t1.ravel(), c1["tvec"])


class _Live:
    """The live service's two answers the calibration route asks for (a rig calibrated earlier)."""

    def __init__(self, calibrations: dict[str, dict]) -> None:
        self.calibrations = calibrations

    def has_rig(self, name: str) -> bool:
        return name in self.calibrations

    def calibration(self, name: str) -> dict | None:
        return self.calibrations.get(name)

    def estimated_by(self, name: str) -> str | None:  # one replica: every rig is its own
        return None

    def close(self) -> None:
        pass


def test_a_live_rig_calibration_as_toml_and_yaml(tmp_path):
    def cal(rig: dict, source: str) -> dict:
        return {"rig": "lab", "source": source, "frames": 30, "windows": 5, "window_seq": 7, "last_index": 80,
                "lag_windows": 1, "updated_ns": 1, "calibration": rig, "body": {"stature_m": 1.8, "segments": {}},
                "notes": []}

    viewpoints = {"reference": "c0", "source": "viewpoints",
                  "cameras": {"c0": {"rotation": np.eye(3).tolist(), "rotvec": [0, 0, 0],
                                     "euler_xyz_deg": [0, 0, 0], "scale": 1.0}}}
    with ServerThread(make_settings(tmp_path, job_workers=0)) as srv:
        srv.runtime.live = _Live({"lab": cal(_metric_rig(), "self-calibration"), "hall": cal(viewpoints, "viewpoints")})
        assert srv.client.get("/v1/rigs/lab/calibration").json()["window_seq"] == 7  # json, the default
        toml = _get(srv, "/v1/rigs/lab/calibration", "toml").text
        yaml = _get(srv, "/v1/rigs/lab/calibration", "yaml").text
        r = _get(srv, "/v1/rigs/hall/calibration", "yaml", 400)
        assert "no metric cameras" in r.json()["detail"]
        assert srv.client.get("/v1/rigs/lab/calibration", params={"format": "trc"}).status_code == 422
        assert srv.client.get("/v1/rigs/nope/calibration", params={"format": "toml"}).status_code == 404
        srv.runtime.live = None
    cams = {c["name"]: c for c in _anipose_load(toml)}
    assert set(cams) == {"c0", "c1"} and cams["c1"]["matrix"][0, 0] == 900.0
    assert "source = \"posecal live rig\"" in toml and "stature_m = 1.8" in toml
    assert [c[0] for c in _yaml_cameras(yaml)] == ["c0", "c1"]


def test_openapi_declares_the_formats_and_their_media_types():
    from service.app import create_app

    spec = create_app().openapi()
    result = spec["paths"]["/v1/jobs/{job_id}/result"]["get"]
    assert set(result["responses"]["200"]["content"]) == {"application/json", *TEXT.values()}
    assert {"400", "404", "409"} <= set(result["responses"])
    fmt = next(p for p in result["parameters"] if p["name"] == "format")
    assert fmt["schema"]["enum"] == ["json", "trc", "bvh", "csv", "toml", "yaml"] and fmt["schema"]["default"] == "json"
    cal = spec["paths"]["/v1/rigs/{rig}/calibration"]["get"]
    assert set(cal["responses"]["200"]["content"]) == {"application/json", "application/toml", "application/yaml"}
    assert {"400", "404"} <= set(cal["responses"])
