"""Hostile uploads (issue 20, "Uploads"): each attack of the issue's probe, replayed on a real
uvicorn server on 127.0.0.1, is now refused at once with a 4xx naming the file, leaves no
files and no job row, and does not disturb a job that is running."""

from __future__ import annotations

import io
import json
import resource
import struct
import zipfile
import zlib
from pathlib import Path

import cv2
import pytest

from conftest_service import ServerThread, make_settings, sequence_zip, wait_for, write_walk

MAX_FRAMES = 100
WINDOW = 20


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory) -> Path:
    return write_walk(tmp_path_factory.mktemp("seq") / "walk", n_frames=40, seed=1, image_size=(320, 240))


@pytest.fixture(scope="module")
def srv(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("server")
    settings = make_settings(tmp, upload_limit_mb=4.0, unpacked_limit_mb=8.0, max_frames=MAX_FRAMES,
                             window_length=WINDOW, window_hop=10)
    with ServerThread(settings) as server:
        yield server


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png(width: int, height: int, *, real: bool = True) -> bytes:
    """A grey PNG of ``width`` x ``height`` zeros, compressed row by row (the test never holds
    the pixels); ``real=False``: only the header is right, the pixel data is a stub."""
    comp = zlib.compressobj(9)
    if real:
        row = b"\0" * (width + 1)
        idat = b"".join(comp.compress(row) for _ in range(height)) + comp.flush()
    else:
        idat = comp.compress(b"\0" * 64) + comp.flush()
    return (b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + _chunk(b"IDAT", idat) + _chunk(b"IEND", b""))


def _zip(files: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _sequence_files(seq_dir: Path, **replace: bytes) -> dict[str, bytes]:
    """The sequence folder as zip members under walk/, with some members replaced or added."""
    files = {f"walk/{p.relative_to(seq_dir)}": p.read_bytes() for p in sorted(seq_dir.rglob("*")) if p.is_file()}
    files.update({f"walk/{k}": v for k, v in replace.items()})
    return files


def _rig(seq_dir: Path, **fields) -> bytes:
    return json.dumps({**json.loads((seq_dir / "rig.json").read_text()), **fields}).encode()


def _submit(srv: ServerThread, data: bytes, name: str = "walk.zip"):
    return srv.client.post("/v1/jobs", files={"files": (name, data, "application/zip")})


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def _refused(r, status: int, *words: str) -> str:
    assert r.status_code == status, r.text
    detail = r.json()["detail"]
    for w in words:
        assert w in detail, detail
    return detail


def _nothing_left(srv: ServerThread, keep: set[str]) -> None:
    """No job row and no upload folder beyond ``keep``."""
    assert {j["id"] for j in srv.client.get("/v1/jobs", params={"limit": 1000}).json()["jobs"]} == keep
    data = srv.settings.data_dir
    assert ({p.name for p in data.iterdir()} if data.exists() else set()) == keep


def _done(srv: ServerThread, job_id: str, timeout: float = 120.0) -> dict:
    return wait_for(lambda: (j := srv.client.get(f"/v1/jobs/{job_id}").json())["state"]
                    in ("done", "failed", "cancelled") and j, timeout=timeout, what=f"job {job_id}")


def test_a_huge_png_in_a_small_zip_is_refused_from_its_header(srv, seq_dir):
    """Issue: a 152 KB zip holding one 20000x20000 PNG -> 422 only after +750-930 MB; with
    image_size 20000x20000 in rig.json it was accepted and a worker reached 2 GB."""
    huge = _png(20000, 20000)  # a valid PNG: decoding it would take 400 MB
    upload = _zip(_sequence_files(seq_dir, **{"c0/000005.png": huge}))
    assert len(upload) < 1 << 20
    before = _peak_rss_mb()
    r = _submit(srv, upload)
    _refused(r, 413, "c0/000005.png", "PNG header says 20000x20000")
    # The same with the rig claiming frames that large: refused from rig.json.
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c0/000005.png": huge,
                                                       "rig.json": _rig(seq_dir, image_size=[20000, 20000])})))
    _refused(r, 413, "rig.json", "image_size 20000x20000")
    # Nothing was decoded: the server (this process) did not grow by the PNG's 400 MB.
    assert _peak_rss_mb() - before < 100, (before, _peak_rss_mb())
    _nothing_left(srv, set())


def test_a_header_claiming_100000_squared_is_413_and_leaves_nothing(srv, seq_dir):
    """Issue: 500, and the unpacked upload (with padding: 704 MB) left in the data directory."""
    padding = b"\0" * (6 << 20)  # within the unpacked limit (8 MB), compressed to a few KB
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c1/000003.png": _png(100000, 100000, real=False),
                                                       "padding.bin": padding})))
    _refused(r, 413, "c1/000003.png", "100000x100000")
    _nothing_left(srv, set())


def test_a_frame_number_far_beyond_the_limit_is_refused_from_the_zip_directory(srv, seq_dir):
    """Issue: a frame named 150000000.png -> 413 after +1.2 GB and 10 s."""
    png = (seq_dir / "c0" / "000001.png").read_bytes()
    before = _peak_rss_mb()
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c0/150000000.png": png})))
    _refused(r, 413, "walk/c0/150000000.png", f"limit of {MAX_FRAMES} frames")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c0/" + "9" * 5000 + ".png": png})))
    _refused(r, 413, "frame number")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c0/\u00b2\u00b3.png": png})))  # digits, not ASCII
    _refused(r, 422, "c0/\u00b2\u00b3.png", "named by frame number")
    assert _peak_rss_mb() - before < 100
    _nothing_left(srv, set())


def _corrupt_deflate(upload: bytes, member: str) -> bytes:
    """The zip with ``member``'s compressed bytes damaged (headers intact: only reading it,
    as ``testzip()`` does, finds the damage)."""
    data = bytearray(upload)
    zf = zipfile.ZipFile(io.BytesIO(upload))
    info = zf.getinfo(member)
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    for k in range(start + 2, start + min(40, info.compress_size - 1)):
        data[k] ^= 0xA5
    return bytes(data)


def test_damaged_zips_are_400_naming_the_member(srv, seq_dir):
    """Issue: a corrupt zip whose damage shows in testzip() -> 500."""
    member = "walk/c1/000010.png"
    upload = _corrupt_deflate(_zip(_sequence_files(seq_dir)), member)
    with zipfile.ZipFile(io.BytesIO(upload)) as zf, pytest.raises(zlib.error):
        zf.testzip()  # what made it a 500: testzip() lets zlib.error through
    _refused(_submit(srv, upload), 400, "corrupt zip", member)
    # A member whose header declares fewer bytes than it holds (the count while extracting).
    lying = bytearray(_zip({"walk/rig.json": _rig(seq_dir), "walk/c0/000000.png": b"\0" * (1 << 20)}))
    for offset in (lying.find(b"PK\x03\x04", 10) + 22, lying.find(b"PK\x01\x02", lying.find(b"PK\x01\x02") + 4) + 24):
        lying[offset:offset + 4] = struct.pack("<I", 100)
    _refused(_submit(srv, bytes(lying)), 400, "corrupt zip", "walk/c0/000000.png")
    # Declared sizes beyond the unpacked limit: refused before extracting anything.
    bomb = _zip({"walk/rig.json": _rig(seq_dir), "walk/a.bin": b"\0" * (5 << 20), "walk/b.bin": b"\0" * (5 << 20)})
    assert len(bomb) < 100_000
    _refused(_submit(srv, bomb), 413, "expands to", "limit")
    _refused(_submit(srv, _zip({"/tmp/posecal-escape.txt": b"x", "walk/rig.json": b"{}"})), 400, "outside")
    _nothing_left(srv, set())


def test_bad_sequence_files_are_422_naming_the_file(srv, seq_dir):
    png = (seq_dir / "c0" / "000004.png").read_bytes()
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"c0/000004.png": png[: len(png) // 2]})))
    _refused(r, 422, "c0/000004.png", "not a readable PNG")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"rig.json": b"[" * 100_000})))
    _refused(r, 422, "rig.json nests too deeply")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"rig.json": _rig(seq_dir, cameras=["c0", "../../etc"])})))
    _refused(r, 422, "'../../etc'")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"rig.json": _rig(seq_dir, image_size=[1e400, 240])})))
    _refused(r, 422, "rig.json")
    r = _submit(srv, _zip(_sequence_files(seq_dir, **{"rig.json": _rig(seq_dir, cameras=[f"c{i}" for i in range(40)])})))
    _refused(r, 413, "40 cameras")
    _nothing_left(srv, set())


def _video(path: Path, frames: int, size: tuple[int, int] = (320, 240)) -> Path:
    """An MJPG AVI of a synthetic walker (12 empty frames first)."""
    from capture.synthetic import SyntheticSource

    src = SyntheticSource.from_spec(f"seed=3,azimuth=60,elevation=10,empty=12,pass=60,gap=0,"
                                    f"size={size[0]}x{size[1]}")
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 15, size)
    for i in range(frames):
        writer.write(src.render(i).image)
    writer.release()
    src.close()
    return path


def _truncated(path: Path, keep: int) -> bytes:
    """The video cut after ``keep`` of its frames' JPEG data (the header still counts them all)."""
    data = path.read_bytes()
    ends = [k for k in range(len(data)) if data.startswith(b"00dc", k)]
    return data[: ends[keep]]


def _videos(files: dict[str, bytes]) -> list:
    return [("files", (name, data, "video/x-msvideo")) for name, data in files.items()]


# The videos' decoding is under test, not the posture: the model's placement is cheaper.
LIGHT = {"warmup": "10", "posture": "model"}


def test_videos_checked_from_their_header_and_truncation_reported(srv, seq_dir, tmp_path):
    """Issue: a truncated AVI whose header promises 80 frames (33 decode) -> the camera was
    estimated from what was left, 118 deg off, with no note."""
    running = _submit(srv, sequence_zip(seq_dir))  # a job runs while the bad uploads come in
    assert running.status_code == 202, running.text
    long = _video(tmp_path / "long.avi", MAX_FRAMES + 20, size=(64, 48))
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": long.read_bytes()}))
    _refused(r, 413, "'c0.avi'", f"header counts {MAX_FRAMES + 20} frames")
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": b"RIFF" + b"\0" * 400}))
    _refused(r, 422, "'c0.avi'", "cannot be decoded")

    full = _video(tmp_path / "c.avi", 80)
    c1 = full.read_bytes()
    mostly = _truncated(full, 45)  # 45 of 80 frames: estimated, with a note
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": mostly, "c1.avi": c1}), data=LIGHT)
    assert r.status_code == 202, r.text
    marked = r.json()["id"]
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": _truncated(full, 15), "c1.avi": c1}),
                        data=LIGHT)
    assert r.status_code == 202, r.text  # the header is fine; decoding finds it short
    short = r.json()["id"]
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": _truncated(full, 15), "c1.avi": _truncated(full, 12)}),
                        data=LIGHT)
    assert r.status_code == 202, r.text
    broken = r.json()["id"]

    assert _done(srv, running.json()["id"])["state"] == "done"
    job = _done(srv, marked)
    assert job["state"] == "done", job
    result = srv.client.get(f"/v1/jobs/{marked}/result").json()
    cam = result["cameras"]["c0"]
    assert cam["header_frames"] == 80 and 40 <= cam["decoded_frames"] < 80, cam
    assert any("header counts 80" in n for n in cam["notes"]) and any("c0:" in n for n in result["notes"])
    assert result["cameras"]["c1"]["decoded_frames"] == result["cameras"]["c1"]["header_frames"] == 80
    assert not any(n.startswith("c1:") for n in result["notes"])
    job = _done(srv, short)  # c0 decodes less than a window: left out, named; c1 goes on
    assert job["state"] == "done", job
    result = srv.client.get(f"/v1/jobs/{short}/result").json()
    assert list(result["cameras"]) == ["c1"], list(result["cameras"])
    assert any(n.startswith("c0: left out, video c0.avi: only ") and "of the 80 frames" in n
               and "fewer than one window" in n for n in result["notes"]), result["notes"]
    job = _done(srv, broken)  # nothing left: the job fails, every video named
    assert job["state"] == "failed" and "c0.avi" in job["error"] and "c1.avi" in job["error"], job
    assert "fewer than one window" in job["error"], job
    _nothing_left(srv, {running.json()["id"], marked, short, broken})
    metrics = srv.client.get("/metrics").text
    for status in ("400", "413", "422"):
        assert f'posecal_uploads_rejected_total{{status="{status}"}}' in metrics


def test_an_image_of_the_empty_scene_beside_a_video_is_its_background(srv, tmp_path):
    """``<camera>.background.png`` uploaded with the videos is kept beside its video for the segmenter
    (:func:`capture.refine.segment_clip`; the result says whether it was used); one that is not the
    video's size (read from its header), not an image, or for no camera is 422 naming it."""
    from capture.synthetic import SyntheticSource

    video = _video(tmp_path / "c.avi", 45).read_bytes()
    src = SyntheticSource.from_spec("seed=3,azimuth=60,elevation=10,empty=12,pass=60,gap=0,size=320x240")
    empty = cv2.imencode(".png", src.render(0).image)[1].tobytes()  # before the walker comes in
    src.close()
    small = cv2.imencode(".png", cv2.resize(src.render(0).image, (160, 120)))[1].tobytes()
    before = {j["id"] for j in srv.client.get("/v1/jobs", params={"limit": 1000}).json()["jobs"]}
    for plate, status, words in (({"c0.background.png": small}, 422, ("c0.background.png is 160x120", "320x240")),
                                 ({"c2.background.jpg": empty}, 422, ("c2.background.jpg", "no video")),
                                 ({"c1.background.png": _png(100000, 100000, real=False)}, 422,
                                  ("c1.background.png is 100000x100000",)),  # from its header
                                 ({"c1.background.png": b"\x89PNG not really"}, 422, ("c1.background.png",
                                                                                      "not a readable image"))):
        r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": video, "c1.avi": video, **plate}), data=LIGHT)
        _refused(r, status, *words)
    _nothing_left(srv, before)
    r = srv.client.post("/v1/jobs", files=_videos({"c0.avi": video, "c1.avi": video, "c0.background.png": empty}),
                        data=LIGHT)
    assert r.status_code == 202, r.text
    job = _done(srv, r.json()["id"])
    assert job["state"] == "done", job
    result = srv.client.get(f"/v1/jobs/{job['id']}/result").json()
    # the walker crosses the view: the clip's own background is the better one, and the note says so
    assert any(n.startswith("c0: background: learned from the clip, not c0.background.png")
               for n in result["notes"]), result["notes"]
    assert not any(n.startswith("c1: background") for n in result["notes"])
