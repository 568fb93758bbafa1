"""Hostile peers on the Zenoh key space (issue 20, "Wire"): each forged message of the issue's
probe, sent from a real Zenoh session on 127.0.0.1 to a real service, is now a counted
rejection or drop; the rig's real cameras and windows go on."""

from __future__ import annotations

import json
import logging
import struct
import threading
import time
import zlib

import numpy as np
import pytest
import zenoh

from capture.receiver import SilhouetteReceiver, ValidatingSubscriber
from capture.wire import (Box, FeedbackMessage, SilhouetteMessage, WireError, decode, encode, feedback_key,
                          silhouette_key)
from capture.zconfig import build_config
from conftest_service import ServerThread, make_settings, wait_for
from estimator.synth import SynthSpec, synthesize
from service.server import free_port

RIG = "lab"
SIZE = (320, 240)
N_FRAMES = 80
FPS = 30.0
BLOCK = zenoh.CongestionControl.BLOCK  # as agents publish: nothing dropped on the way


def _envelope(header: dict | bytes, png: bytes = b"", kind: int = 1) -> bytes:
    head = header if isinstance(header, bytes) else json.dumps(header).encode()
    return struct.pack(">4sBBI", b"PCAL", 1, kind, len(head)) + head + png


def _png_header(width: int, height: int) -> bytes:
    """A PNG whose header claims ``width`` x ``height`` (its data is a stub)."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def _header(**fields) -> dict:
    base = dict(rig=RIG, camera="c0", frame_index=1, capture_ns=time.time_ns(), box=[0, 0, 4, 4],
                image_size=list(SIZE), epoch_ns=1, seq=0, sync="index", publish_ns=0)
    return {**base, **fields}


# ------------------------------------------------------------------ decoding, no network


@pytest.mark.parametrize("payload, code, reason", [
    (_envelope(_header(box=[0, 0, 100000, 100000], image_size=[100000, 100000]), _png_header(100000, 100000)),
     "image", "image_size must be"),
    (_envelope(_header(box=[0, 0, 4, 4]), _png_header(100000, 100000)), "image", "does not match box size"),
    (_envelope(b"[" * 30000 + b"]" * 30000), "header", "nested too deeply"),
    (_envelope(_header(frame_index=2 ** 80, box=[0, 0, 0, 0])), "field", "'frame_index' must be an integer"),
    (_envelope({"rig": RIG, "camera": "c0", "frame_index": 1, "box": [0, 0, 16384, 16384],
                "image_size": [16384, 16384], "issued_ns": 0}, b"\x89PNG", kind=2), "image", "image_size must be"),
])
def test_hostile_payloads_are_wire_errors_with_a_code(payload, code, reason):
    """Issue: a PNG header claiming 100000^2 and a deeply nested JSON header escaped as
    uncaught exceptions; a 225-byte prior claiming 16384^2 cost an agent 256 MB."""
    assert len(payload) < 130_000
    with pytest.raises(WireError, match=reason) as exc:
        decode(payload)
    assert exc.value.code == code


# ------------------------------------------------------------------- real Zenoh sessions


def _crop(sil: np.ndarray | None) -> tuple[Box, np.ndarray]:
    if sil is None or not sil.any():
        return Box(0, 0, 0, 0), np.zeros((0, 0), np.uint8)
    ys, xs = np.nonzero(sil)
    x0, y0, x1, y1 = xs.min(), ys.min(), xs.max() + 1, ys.max() + 1
    return Box(int(x0), int(y0), int(x1 - x0), int(y1 - y0)), np.ascontiguousarray(sil[y0:y1, x0:x1])


@pytest.fixture(scope="module")
def crops() -> dict[str, list[tuple[Box, np.ndarray]]]:
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=N_FRAMES, seed=1, azimuths=(60.0, 150.0),
                               elevations=(10.0, 10.0), image_size=SIZE))
    return {cam: [_crop(s) for s in seq.silhouettes[cam]] for cam in seq.cameras}


class _Agents:
    """Index-synchronised cameras of one rig published from one real Zenoh session, as
    agents would (one epoch and sequence per camera)."""

    def __init__(self, session: zenoh.Session, crops: dict, rig: str = RIG) -> None:
        self.session, self.crops, self.rig = session, crops, rig
        self.epochs = {cam: time.time_ns() for cam in crops}
        self.pubs = {cam: session.declare_publisher(silhouette_key(rig, cam), congestion_control=BLOCK)
                     for cam in crops}

    def message(self, cam: str, k: int, **overrides) -> SilhouetteMessage:
        box, mask = self.crops[cam][k % N_FRAMES]
        fields = dict(rig=self.rig, camera=cam, frame_index=k, capture_ns=time.time_ns(), box=box,
                      image_size=SIZE, epoch_ns=self.epochs[cam], seq=k, mask=mask, sync="index",
                      publish_ns=time.time_ns())
        return SilhouetteMessage(**{**fields, **overrides})

    def stream(self, frames: range, inject=None) -> None:
        """Publish ``frames`` of every camera at FPS; ``inject(k)`` runs before frame k."""
        t0 = time.monotonic()
        for n, k in enumerate(frames):
            if inject is not None:
                inject(k)
            for cam, pub in self.pubs.items():
                pub.put(encode(self.message(cam, k)))
            time.sleep(max(0.0, t0 + (n + 1) / FPS - time.monotonic()))


def _live_settings(tmp_path, **overrides):
    return make_settings(tmp_path, live=True, job_workers=0, feedback=False, window_length=20,
                         window_hop=10, max_wait_ms=400.0, **overrides)


def _metric(text: str, name: str) -> float:
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines() if line.startswith(name))


def _estimates(srv: ServerThread, rig: str = RIG) -> list[dict]:
    r = srv.client.get(f"/v1/rigs/{rig}/estimates", params={"since": 0, "limit": 1000})
    return r.json()["estimates"] if r.status_code == 200 else []


def _windows_through(srv: ServerThread, last_index: int) -> list[dict]:
    return wait_for(lambda: (e := _estimates(srv)) and e[-1]["window"]["last_index"] >= last_index and e,
                    timeout=60, what=f"a window through frame {last_index}")


def test_forged_epoch_and_index_do_not_cut_out_a_camera_or_stop_the_rig(tmp_path, crops, caplog):
    """Issue: one forged silhouette with epoch_ns = 2**62 cut that camera out of every later
    window for good; one with frame_index = 2**62 and a sniffed epoch stopped the rig."""
    caplog.set_level(logging.INFO)
    settings = _live_settings(tmp_path)
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=settings.zenoh_listen)) as session:
        agents = _Agents(session, crops)
        time.sleep(0.5)  # let the session find the service

        def forge(k: int) -> None:
            if k == 25:  # a stranger's camera c0 "from the far future": would become its epoch
                agents.pubs["c0"].put(encode(agents.message("c0", k, epoch_ns=2 ** 62)))
            if k == 45:  # c1's real epoch (sniffed), an index far ahead: would close a frame there
                agents.pubs["c1"].put(encode(agents.message("c1", k, frame_index=2 ** 62, seq=k)))
                agents.pubs["c1"].put(encode(agents.message("c1", k, frame_index=k + 10_000, seq=k)))

        agents.stream(range(N_FRAMES), inject=forge)
        estimates = _windows_through(srv, N_FRAMES - 1)
        rig = srv.client.get(f"/v1/rigs/{RIG}").json()
        metrics = srv.client.get("/metrics").text
    # Every window after the forgeries has both cameras: c0 was not shut out, the rig went on.
    after = [e for e in estimates if e["window"]["first_index"] > 45]
    assert len(after) >= 2 and all(e["window"]["cameras"] == ["c0", "c1"] for e in after), \
        [e["window"] for e in estimates]
    assert [e["window"]["last_index"] for e in estimates][-1] == N_FRAMES - 1
    assert rig["cameras"]["c0"]["epoch_ns"] == agents.epochs["c0"] and rig["frames"]["restarts"] == 0
    assert rig["cameras"]["c1"]["last_index"] == N_FRAMES - 1
    assert _metric(metrics, 'posecal_receiver_rejected_by_reason_total{reason="epoch_future"}') == 1
    assert _metric(metrics, 'posecal_frames_dropped_total{reason="index_ahead",rig="lab"}') == 2
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"


def test_a_rig_whose_indices_really_jump_is_followed(tmp_path, crops):
    """The guard against indices from the future does not stop a rig whose cameras all
    jumped (a recorded source that skipped): a few frames in a row that agree move it."""
    settings = _live_settings(tmp_path)
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=settings.zenoh_listen)) as session:
        agents = _Agents(session, crops)
        time.sleep(0.5)
        agents.stream(range(40))
        agents.stream(range(5040, 5080))
        estimates = _windows_through(srv, 5070)  # windows restart at the jump (a gap): 5044-5063, 5054-5073
        metrics = srv.client.get("/metrics").text
    assert estimates[-1]["window"]["cameras"] == ["c0", "c1"] and estimates[-1]["window"]["first_index"] >= 5040
    dropped = _metric(metrics, 'posecal_frames_dropped_total{reason="index_ahead",rig="lab"}')
    assert 0 < dropped <= 8  # the frames before the jump was believed


def test_a_flood_of_forged_rigs_is_capped_and_expires(tmp_path, crops):
    """Issue: 2,000 forged rig names were all kept (/v1/rigs 769 KB, /metrics 278 KB)."""
    settings = _live_settings(tmp_path, max_rigs=8, max_cameras=4, rig_expiry_s=5.0)
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=settings.zenoh_listen)) as session:
        agents = _Agents(session, crops)
        time.sleep(0.5)
        real = threading.Thread(target=agents.stream, args=(range(N_FRAMES),))
        real.start()
        wait_for(lambda: srv.client.get(f"/v1/rigs/{RIG}").status_code == 200, timeout=5, what="the real rig")
        forger = _Agents(session, {"c0": crops["c0"]}, rig="x")
        for i in range(2000):
            session.put(silhouette_key(f"forged{i}", "c0"), encode(forger.message("c0", i, rig=f"forged{i}")),
                        congestion_control=BLOCK)
        for i in range(20):  # and forged cameras on the real rig
            session.put(silhouette_key(RIG, f"cam{i}"), encode(forger.message("c0", 0, rig=RIG, camera=f"cam{i}")),
                        congestion_control=BLOCK)
        rigs = wait_for(lambda: len(r := srv.client.get("/v1/rigs").json()["rigs"]) == 8 and r, timeout=10,
                        what="the rigs to fill up")
        assert RIG in [r["rig"] for r in rigs]
        wait_for(lambda: len(srv.rig(RIG).get("cameras", ())) == 4, timeout=10,
                 what="the real rig's cameras to fill up")
        real.join(timeout=30)
        estimates = _windows_through(srv, N_FRAMES - 1)
        assert len(srv.client.get("/v1/rigs").json()["rigs"]) <= 8
        # Silent rigs are forgotten, with their metrics; the real rig is kept.
        wait_for(lambda: [r["rig"] for r in srv.client.get("/v1/rigs").json()["rigs"]] == [RIG]
                 or srv.client.get("/v1/rigs").json()["rigs"] == [], timeout=10, what="forged rigs to expire")
        metrics = srv.client.get("/metrics").text
    assert "forged" not in metrics and len(metrics) < 60_000
    refused = _metric(metrics, 'posecal_live_refused_total{reason="rig_limit"}')
    forgotten = _metric(metrics, "posecal_rigs_forgotten_total")
    assert refused + forgotten >= 2000 - 8 and refused > 0
    assert _metric(metrics, 'posecal_live_refused_total{reason="camera_limit"}') > 0
    assert estimates[-1]["window"]["cameras"] == ["c0", "c1"]


def test_malformed_messages_are_counted_by_reason_without_tracebacks(tmp_path, crops, caplog):
    """Issue: a PNG header claiming 100000^2 and a deeply nested JSON header escaped validation
    as uncaught exceptions (full tracebacks in the log, uncounted)."""
    caplog.set_level(logging.INFO)
    settings = _live_settings(tmp_path)
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=settings.zenoh_listen)) as session:
        agents = _Agents(session, crops)
        time.sleep(0.5)
        pub = session.declare_publisher(silhouette_key(RIG, "c0"), congestion_control=BLOCK)

        def attack(k: int) -> None:
            if k != 30:
                return
            pub.put(_envelope(_header(box=[0, 0, 4, 4]), _png_header(100000, 100000)))
            pub.put(_envelope(b"[" * 30000 + b"]" * 30000))
            pub.put(_envelope(_header(box=[0, 0, 16384, 16384], image_size=[16384, 16384]),
                              _png_header(16384, 16384)))
            pub.put(encode(agents.message("c0", k, capture_ns=2 ** 62, sync="time")))
            pub.put(b"PCAL")

        agents.stream(range(N_FRAMES), inject=attack)
        estimates = _windows_through(srv, N_FRAMES - 1)
        metrics = srv.client.get("/metrics").text
    by_reason = {code: _metric(metrics, f'posecal_receiver_rejected_by_reason_total{{reason="{code}"}}')
                 for code in ("image", "header", "capture_future", "envelope")}
    assert by_reason == {"image": 2, "header": 1, "capture_future": 1, "envelope": 1}, by_reason
    assert _metric(metrics, "posecal_receiver_rejected_total") == 5
    assert not [r for r in caplog.records if r.exc_info], "a traceback was logged"
    lines = [r.getMessage() for r in caplog.records if "rejected message" in r.getMessage()]
    assert len(lines) == 5 and all("\n" not in line and len(line) < 700 for line in lines)
    assert all(e["window"]["cameras"] == ["c0", "c1"] for e in estimates)


def test_a_prior_claiming_a_huge_image_never_reaches_an_agent():
    """Issue: a 225-byte prior claiming a 16384^2 image cost an agent 256 MB and 3-4 s of CPU
    on Zenoh's callback thread."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    got: list[FeedbackMessage] = []
    with zenoh.open(build_config(listen=[endpoint])) as agent_session, \
            ValidatingSubscriber(agent_session, feedback_key(RIG, "c0"), FeedbackMessage,
                                 on_message=got.append, max_image_size=SIZE) as priors, \
            SilhouetteReceiver(agent_session, RIG, max_clock_ahead_s=5.0) as silhouettes, \
            zenoh.open(build_config(connect=[endpoint])) as stranger:
        pub = stranger.declare_publisher(feedback_key(RIG, "c0"), congestion_control=BLOCK)
        assert wait_for(lambda: pub.matching_status.matching, timeout=5, what="the agent's subscriber")
        huge = _envelope({"rig": RIG, "camera": "c0", "frame_index": 1, "box": [0, 0, 16384, 16384],
                          "image_size": [16384, 16384], "issued_ns": 0}, _png_header(16384, 16384), kind=2)
        assert len(huge) < 300
        pub.put(huge)
        larger = FeedbackMessage(rig=RIG, camera="c0", frame_index=1, box=Box(0, 0, 4, 4),
                                 image_size=(4000, 3000), mask=np.full((4, 4), 255, np.uint8))
        pub.put(encode(larger))  # valid on the wire, but larger than this agent's frames
        fine = FeedbackMessage(rig=RIG, camera="c0", frame_index=2, box=Box(0, 0, 4, 4),
                               image_size=SIZE, mask=np.full((4, 4), 255, np.uint8))
        pub.put(encode(fine))
        wait_for(lambda: got, timeout=5, what="the valid prior")
        wait_for(lambda: priors.stats().rejected == 2, timeout=5, what="two rejections")
        # A silhouette stamped in the far future is rejected, not adopted as the camera's epoch.
        sil = stranger.declare_publisher(silhouette_key(RIG, "c0"), congestion_control=BLOCK)
        wait_for(lambda: sil.matching_status.matching, timeout=5, what="the receiver")
        mask = np.full((4, 4), 255, np.uint8)
        base = dict(rig=RIG, camera="c0", frame_index=1, box=Box(0, 0, 4, 4), image_size=SIZE, seq=0,
                    mask=mask, sync="index")
        sil.put(encode(SilhouetteMessage(**base, capture_ns=time.time_ns(), epoch_ns=2 ** 62)))
        now = time.time_ns()
        sil.put(encode(SilhouetteMessage(**base, capture_ns=now, epoch_ns=now - 10**9)))
        item = silhouettes.get(timeout=5)
        stats = silhouettes.stats()
    assert [p.frame_index for p in got] == [2]
    assert priors.stats().codes == {"image": 2}
    assert item is not None and item.message.epoch_ns == now - 10**9 and item.new_epoch
    assert stats.codes == {"epoch_future": 1} and stats.accepted == 1
