"""Live path: frame assembly, windows and smoothing (units), then real agents on
loopback Zenoh streaming to a real uvicorn server that estimates every window."""

from __future__ import annotations

import dataclasses
import json
import re
import threading
import time

import cv2
import numpy as np
import pytest
import zenoh

from capture.agent import AgentSettings, AgentStats
from capture.agent import main as agent_main
from capture.segment import SegmentSettings
from capture.sources import FrameSource
from capture.synthetic import SyntheticSource
from capture.wire import Box, FeedbackMessage, SilhouetteMessage, decode, encode, estimate_key, feedback_key
from capture.zconfig import build_config
from conftest_service import ServerThread, make_settings, wait_for
from estimator.windows import ViewpointTrack
from service.schemas import LiveCalibration, LiveEstimate
from service.live import FrameAssembler, WindowBuffer

# Real-time streams and timeouts: run alone, not beside another test (README "Tests").
pytestmark = pytest.mark.serial

# ----------------------------------------------------------------------------- units


def _msg(cam: str, index: int, *, capture_ns: int | None = None, sync: str = "index", empty: bool = False):
    mask = np.zeros((0, 0), np.uint8) if empty else np.full((4, 2), 255, np.uint8)
    box = Box(0, 0, 0, 0) if empty else Box(10, 10, 2, 4)
    return SilhouetteMessage(rig="r", camera=cam, frame_index=index,
                             capture_ns=capture_ns or 1_000_000_000 + index * 66_666_667,
                             box=box, image_size=(64, 48), epoch_ns=1, seq=index, mask=mask, sync=sync)


def _assembler(*, discovered: bool = True, **kw) -> FrameAssembler:
    a = FrameAssembler(**{"tolerance_ms": 20.0, "max_wait_ms": 100.0, "camera_timeout_s": 3.0, **kw})
    if discovered:
        a._started = -10.0  # past the start-up discovery period
    return a


def test_assembler_waits_for_cameras_at_start_up():
    a = _assembler(discovered=False)
    assert a.add(_msg("c0", 0), 0, 0.0) == []  # the first frames wait for the other cameras
    assert a.add(_msg("c1", 0), 0, 0.03) == []
    assert a.add(_msg("c0", 1), 0, 0.04) == []
    out = a.add(_msg("c1", 1), 0, 0.12)
    assert [sorted(fs.parts) for fs in out] == [["c0", "c1"], ["c0", "c1"]] and a.late == 0


def test_assembler_groups_by_index_and_counts_late_duplicate_missing():
    a = _assembler()
    out = a.add(_msg("c0", 0), 0, 0.0)
    assert [fs.index for fs in out] == [0]  # the only camera known: complete at once
    a.last_seen["c1"] = 0.0  # c1 becomes known
    out = a.add(_msg("c0", 1), 0, 0.0)
    assert out == []  # waits for c1
    out = a.add(_msg("c1", 1), 0, 0.01)
    assert [sorted(fs.parts) for fs in out] == [["c0", "c1"]]
    assert a.add(_msg("c1", 1), 0, 0.02) == [] and a.late == 1  # already closed: late
    a.add(_msg("c0", 2), 0, 0.03)
    assert a.add(_msg("c0", 2), 0, 0.031) == [] and a.duplicate == 1
    # c1 skips frame 2 and sends 3: frame 2 is overtaken and closes without c1.
    out = a.add(_msg("c1", 3), 0, 0.04)
    assert [fs.index for fs in out] == [2] and a.missing == 1
    # c1 goes silent: frame 4 closes after the wait, c1 counted missing.
    a.add(_msg("c0", 3), 0, 0.05)
    a.add(_msg("c0", 4), 0, 0.06)
    assert a.poll(0.07) == []
    assert [fs.index for fs in a.poll(0.5)] == [4] and a.missing == 2


def test_assembler_by_capture_time_within_tolerance():
    a = _assembler()
    a.last_seen.update({"c0": 0.0, "c1": 0.0})
    t0 = 5_000_000_000
    assert a.add(_msg("c0", 7, capture_ns=t0, sync="time"), 0, 0.0) == []
    out = a.add(_msg("c1", 900, capture_ns=t0 + 8_000_000, sync="time"), 0, 0.001)  # 8 ms apart
    assert len(out) == 1 and sorted(out[0].parts) == ["c0", "c1"]
    a.add(_msg("c0", 8, capture_ns=t0 + 66_000_000, sync="time"), 0, 0.002)
    out = a.add(_msg("c1", 901, capture_ns=t0 + 66_000_000 + 30_000_000, sync="time"), 0, 0.003)
    # 30 ms apart: not the same frame; c1's frame overtakes c0's, which closes alone.
    assert [sorted(fs.parts) for fs in out] == [["c0"]]


def test_assembler_learns_a_lagging_camera():
    a = _assembler(max_wait_ms=50.0)
    a.last_seen.update({"c0": 0.0, "c1": 0.0})
    t = 0.0
    for k in range(30):  # c1 arrives 300 ms after c0, every frame
        a.add(_msg("c0", k), 0, t)
        a.poll(t)
        if k >= 4:
            a.add(_msg("c1", k - 4), 0, t)
        t += 0.075
    assert a.lag["c1"] > 0.2
    complete = [fs for fs in a.open if len(fs.parts) == 2]
    assert a.late > 0 and a.late < 10  # only the first frames, before the lag was learned
    assert not complete  # complete sets were emitted, not left open


def test_window_buffer_length_hop_and_gap():
    b = WindowBuffer(length=4, hop=2)
    from service.live import FrameSet

    got = [b.push(FrameSet(i, 0, 0.0)) for i in range(8)]
    windows = [[f.index for f in w] for w in got if w]
    assert windows == [[0, 1, 2, 3], [2, 3, 4, 5], [4, 5, 6, 7]]
    assert b.push(FrameSet(20, 0, 0.0)) is None and b.resets == 1  # gap > length/2: start over


def test_window_buffer_gives_the_frames_of_the_next_window_ahead_of_it():
    """``take_fresh``: the frame sets pushed since the last window (or the last take), once there
    are ``every`` of them: what the live service looks at before the window closes."""
    from service.live import FrameSet

    b = WindowBuffer(length=6, hop=3)
    taken = []
    for i in range(12):
        if b.push(FrameSet(i, 0, 0.0)) is None and (fresh := b.take_fresh(2)) is not None:
            taken.append([f.index for f in fresh])
    # windows close at 5, 8 and 11; between them every two new frames, none left for the window's
    assert taken == [[0, 1], [2, 3], [6, 7], [9, 10]]
    assert b.take_fresh(0) is None
    b.push(FrameSet(12, 0, 0.0))
    b.push(FrameSet(30, 0, 0.0))  # a gap: the frames before are another walk's
    assert [f.index for f in b.take_fresh(1)] == [30]


def test_viewpoint_track_smooths_noise_and_reports_a_move():
    rng = np.random.default_rng(0)
    t = ViewpointTrack(threshold_deg=30.0, confirm=3)
    for k in range(10):
        s = t.update(358.0 + rng.normal(0, 5), 10 + rng.normal(0, 3), k)
    assert abs(((s["azimuth_deg"] - 358.0 + 180) % 360) - 180) < 5 and s["changes"] == []
    s = t.update(180.0, 10.0, 10)  # one wild window: an outlier, not a move
    assert s["changes"] == [] and s["pending_outliers"] == 1
    assert abs(((s["azimuth_deg"] - 358.0 + 180) % 360) - 180) < 5
    for k in range(11, 14):  # the camera really moved to ~90 deg
        s = t.update(90.0 + rng.normal(0, 3), 12.0, k)
    assert len(s["changes"]) == 1 and abs(s["azimuth_deg"] - 90.0) < 6
    assert s["changes"][0]["frame_index"] == 11
    assert t.update(None, None, 14) == s  # a window in which the camera saw nothing


def test_a_first_window_outvoted_by_the_next_is_no_camera_move():
    """A live rig's first window can be its cameras' start-up, 36 deg off (CI, once); the
    windows after it agreeing elsewhere replace it without a move reported (``settle``), and
    a move after that is reported as before."""
    t = ViewpointTrack(threshold_deg=30.0, confirm=3, settle=3)
    t.update(111.0, 0.0, 0)
    for k in range(1, 4):
        s = t.update(75.0, 8.0, k)
    assert s["changes"] == [] and abs(s["azimuth_deg"] - 75.0) < 1
    for k in range(4, 7):
        s = t.update(180.0, 8.0, k)
    assert [c["frame_index"] for c in s["changes"]] == [4]
    plain = ViewpointTrack(threshold_deg=30.0, confirm=3)  # offline (segment_walk): every change counts
    for k, az in enumerate([111.0, 75.0, 75.0, 75.0]):
        s = plain.update(az, 8.0, k)
    assert [c["frame_index"] for c in s["changes"]] == [1]


def test_a_first_window_is_replaced_as_soon_as_two_agree_against_it():
    """A 3-s walk gives a live rig 3 windows: a wrong first one (the agent's track on someone else
    before its first look back) is replaced by the next two agreeing, not kept until a third; an
    established value still needs ``confirm`` windows, and one window never outvotes one."""
    t = ViewpointTrack(threshold_deg=30.0, confirm=3, settle=3)
    t.update(132.0, 0.0, 0)
    assert t.update(13.0, 8.0, 1)["azimuth_deg"] == 132.0  # one against one: kept
    s = t.update(8.0, 8.0, 2)
    assert s["changes"] == [] and abs(s["azimuth_deg"] - 10.5) < 1
    for k in range(3, 5):
        s = t.update(12.0, 8.0, k)
    for k in range(5, 7):  # two windows against a value resting on five: an outlier pair, not a move
        s = t.update(150.0, 8.0, k)
    assert s["changes"] == [] and abs(s["azimuth_deg"] - 11.0) < 2


def _frame_set(index: int, **tracks):
    """A frame set whose cameras' messages are on (agent run, track_id[, track_from])."""
    from service.live import FrameSet

    f = FrameSet(index, 1, 0.0)
    for cam, (epoch, track, *since) in tracks.items():
        f.parts[cam] = dataclasses.replace(_msg(cam, index), epoch_ns=epoch, track_id=track,
                                           track_from=since[0] if since else None)
    return f


def _moves(frames, cam):
    """The camera's look-back moves as the service keeps them from these messages, in order."""
    from service.live import CameraState

    state = CameraState()
    for f in frames:
        if cam in f.parts:
            state.moved(f.parts[cam])
    return state.moves


def test_frames_of_an_earlier_track_of_the_same_agent_run_are_on_another_person():
    from service.live import _on_another_person

    fs = _frame_set
    frames = [fs(0, a=(1, 0), b=(1, None)), fs(1, a=(1, 0), b=(1, None)), fs(2, a=(1, 1), b=(1, None)),
              fs(3, b=(1, None)), fs(4, a=(1, 1), b=(1, None))]
    # an agent that does not say from which frame (no track_from): the earlier track's frames of the window
    assert _on_another_person(frames, "a", _moves(frames, "a")) == [0, 1]
    assert _on_another_person(frames, "b", _moves(frames, "b")) == []  # no track_id: nothing left out
    restarted = [fs(0, a=(1, 3)), fs(1, a=(2, 0)), fs(2, a=(2, 1))]  # the agent restarted: its old run is not judged
    assert _on_another_person(restarted, "a", _moves(restarted, "a")) == [1]
    # track_from: the earlier track was on the walker until frame 1, then on someone else
    said = [fs(0, a=(1, 0)), fs(1, a=(1, 0)), fs(2, a=(1, 0)), fs(3, a=(1, 1, 1)), fs(4, a=(1, 1, 1))]
    moves = _moves(said, "a")
    # a window with frames of both tracks: all of the earlier (one person per window) ...
    assert moves == {(1, 1): 1} and _on_another_person(said, "a", moves) == [0, 1, 2]
    # ... and a window that closed before the move holds only the earlier track: from track_from on,
    # known once the move is
    assert _on_another_person(said[:3], "a", {}) == [] and _on_another_person(said[:3], "a", moves) == [1, 2]


# ----------------------------------------------------------------------- end to end

RIG = "lab"
# Near-side views: the estimator's ahead/behind ambiguity (azimuth a vs 180 - a) is
# smallest there, so the check below tests the service, not that ambiguity.
TRUTH = {"c0": (75.0, 10.0), "c1": (255.0, 10.0)}
# 74 walking frames: a window's priors take ~1 s on a slow 2-core machine, and they go
# to frames ~20 ahead of the window; with 44 the stream ended before any prior could be
# used (CI: 20 priors received, none used).
EMPTY, WALK, WARMUP = 30, 74, 28
FPS = 15.0  # the reference rig


class _Replay(FrameSource):
    """Pre-rendered frames of a synthetic camera (rendering stays out of the timing)."""

    live = False
    hardware_sync = True

    def __init__(self, frames, fps: float, hold=None) -> None:
        self.frames, self.fps, self.hold = frames, fps, hold

    def __iter__(self):
        for f in self.frames:
            if self.hold is not None:
                self.hold(f.index)
            yield type(f)(f.image.copy(), f.index, 0, None)


class _PriorsAhead:
    """Holds the replay's last frames until the service's priors for them have been
    published (seen by the test's own subscriber): each hold at most ``wait_s``, under the
    service's ``camera_timeout_s`` (3 s: a longer silence would close the next frame set
    without the other camera), and at most ``budget_s`` in all (the agents' join).

    Whether priors come before their frames is a timing figure (bench/bench_feedback_live.py),
    not asserted: the feedback renders run at the lowest priority and, on CI's two loaded
    cores, one run's priors came after every frame they were for (c0: 47 received, none
    used). Holding the frames makes the test about what the agents do with priors that
    arrive in time; both cameras wait for the same condition, so they stay in step.
    """

    def __init__(self, session, cameras, hold_from: int, wait_s: float = 2.5, budget_s: float = 8.0) -> None:
        self.seen = {cam: -1 for cam in cameras}
        self.hold_from, self.wait_s, self.budget_s, self.started = hold_from, wait_s, budget_s, None
        self.ready = threading.Condition()
        self.sub = session.declare_subscriber(feedback_key(RIG, "*"), self._heard)

    def _heard(self, sample) -> None:
        msg = decode(sample.payload.to_bytes(), expect=FeedbackMessage)
        with self.ready:
            self.seen[msg.camera] = max(self.seen[msg.camera], msg.frame_index)
            self.ready.notify_all()

    def __call__(self, index: int) -> None:
        if index < self.hold_from:
            return
        with self.ready:
            now = time.monotonic()
            self.started = self.started or now
            timeout = min(self.wait_s, self.started + self.budget_s - now)
            self.ready.wait_for(lambda: min(self.seen.values()) >= index, timeout=max(0.0, timeout))
        time.sleep(0.05)  # the agent's own subscriber hears the same put


@pytest.fixture(scope="module")
def rendered():
    out = {}
    for cam, (az, el) in TRUTH.items():
        src = SyntheticSource.from_spec(f"seed=3,azimuth={az},elevation={el},fps=15,empty={EMPTY},"
                                        f"pass={WALK},gap=0")
        out[cam] = [src.render(i) for i in range(EMPTY + WALK)]
        src.close()
    return out


def _run_agents(endpoint: str, cameras: dict[str, list], keypoints: dict[str, dict] | None = None,
                hold=None, **settings) -> dict[str, AgentStats]:
    """Stream each camera's pre-rendered frames through a real agent (one thread each) at
    ``FPS``, with its ``keypoints`` (frame index -> (13, 2)) when given, each frame first
    passed to ``hold`` when given; returns the agents' stats once every source has run out."""
    stats: dict[str, AgentStats] = {}

    def run(cam: str, frames) -> None:
        stats[cam] = agent_main(
            build_config(connect=[endpoint]),
            AgentSettings(rig=RIG, camera=cam, source="synthetic:", fps=FPS, stats_interval_s=60,
                          segment=SegmentSettings(warmup_frames=WARMUP), **settings),
            source=_Replay(frames, FPS, hold), keypoints=None if keypoints is None else keypoints[cam])

    agents = [threading.Thread(target=run, args=item) for item in cameras.items()]
    for a in agents:
        a.start()
    for a in agents:
        a.join(timeout=30)
    return stats


@pytest.mark.parametrize("feedback", [True, False])
def test_agents_stream_windows_estimated_published_and_served(tmp_path, rendered, feedback):
    """With feedback (§7.1) the service's priors reach the agents and are used; without,
    the agents work as before."""
    # max_wait_ms: how long a frame waits for a camera is a latency budget (bench/bench_service_live.py),
    # not asserted here: with CI's two cores shared by the agents, the service and the estimates, one
    # camera's frame came more than the default 120 ms after the other's (one frame of 182, once).
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=feedback, max_wait_ms=400.0, live_rig=False)  # the rig: its own test
    endpoint = settings.zenoh_listen[0]
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=[endpoint])) as session:
        published = []
        sub = session.declare_subscriber(estimate_key(RIG), lambda s: published.append(json.loads(s.payload.to_bytes())))
        # A malformed message on the key space is rejected and counted; nothing else is disturbed.
        session.put(f"posecal/{RIG}/c0/silhouette", b"not a posecal message")
        time.sleep(0.5)  # let the agents' sessions find the service
        hold = _PriorsAhead(session, rendered, hold_from=EMPTY + WALK - 24) if feedback else None
        stats = _run_agents(endpoint, rendered, hold=hold)
        rig = wait_for(lambda: (r := srv.rig(RIG)) and r["windows"]["estimated"] >= 3 and r,
                       timeout=20, what="three estimated windows")
        sent = EMPTY + WALK - WARMUP
        assert {c: v["frames"] for c, v in rig["cameras"].items()} == {"c0": sent, "c1": sent}
        # The agents finish warming up at different moments: frames that closed before
        # the later camera was heard from cannot take its first frames (late, dropped).
        # That is a start-up transient only: no frame closed without a camera once both were known.
        assert rig["frames"]["late"] <= 30 and rig["frames"]["duplicate"] == 0
        assert rig["frames"]["missing"] == 0

        est = srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": 0}).json()["estimates"]
        assert len(est) == rig["windows"]["estimated"]
        for e in est:
            assert e["window"]["frames"] == 20 and e["window"]["cameras"] == ["c0", "c1"]
            assert len(e["frames"]) == 20 and len(e["frames"][0]["joints3d"]) == 13
            assert e["frames"][-1]["index"] == e["window"]["last_index"]
        seqs = [e["window"]["seq"] for e in est]
        assert seqs == sorted(seqs)
        later = srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": seqs[0]}).json()["estimates"]
        assert [e["window"]["seq"] for e in later] == seqs[1:]

        latest = srv.client.get(f"/v1/rigs/{RIG}/estimate").json()
        for cam, (az, el) in TRUTH.items():
            sm = latest["smoothed"][cam]
            # 45 deg: the agents' segmentation (MOG2 after 28 background frames) costs
            # this walker up to ~35 deg with the small test model; swapped cameras
            # (180 deg apart) still fail.
            assert abs((sm["azimuth_deg"] - az + 180) % 360 - 180) < 45, (cam, sm)
            assert sm["changes"] == []
        wait_for(lambda: len(published) >= len(est), timeout=5, what="published estimates")
        assert {p["window"]["seq"] for p in published} >= set(seqs)

        if feedback:  # priors flowed back, ahead of their frames, and the agents used them
            assert rig["feedback"]["priors_sent"] > 0
            for cam, st in stats.items():
                assert st.priors > 0 and st.prior_use.used > 0, (cam, st.prior_use, rig["feedback"])
                # Priors are predicted for frames still to come and were used on them (above).
                # How many arrived before their frame's capture time is a timing figure (95 %
                # target, bench/bench_feedback_live.py, 96.3 % on an idle machine), not asserted
                # here: under CPU contention it dropped below one half, and to 0 with the load
                # at 4 on two cores (priors then come after capture but before segmentation,
                # and are still used). None came for another run.
                assert st.priors_other_epoch == 0, (cam, st)
        else:
            assert rig["feedback"]["priors_sent"] == 0
            assert all(st.priors == 0 and st.prior_use.used == 0 for st in stats.values())
        assert srv.client.get("/v1/rigs").json()["rigs"][0]["rig"] == RIG
        assert srv.client.get("/v1/rigs/nope").status_code == 404
        assert srv.client.get("/v1/rigs/nope/estimate").status_code == 404
        metrics = srv.client.get("/metrics").text
        assert "posecal_receiver_rejected_total 1.0" in metrics
        assert f'posecal_frames_in_total{{camera="c0",rig="{RIG}"}} {float(sent)}' in metrics
        assert "posecal_window_latency_seconds_count" in metrics
        # The windows' frames went to the live workers ahead of each close (warm_every), in their idle time.
        warmed = re.search(r'posecal_frames_warmed_total\{outcome="sent"\} (\d+)', metrics)
        assert warmed and int(warmed.group(1)) > 0, [m for m in metrics.splitlines() if "warmed" in m]
        sub.undeclare()


BYSTANDER = EMPTY + 8  # from this frame on, c0 sees a second person standing at its right edge


def _with_bystander(frame):
    """The frame with a person-sized figure standing away from the walker's path."""
    if frame.index < BYSTANDER:
        return frame
    image = frame.image.copy()
    cv2.ellipse(image, (600, 120), (14, 45), 0, 0, 360, (30, 150, 40), -1)
    return type(frame)(image, frame.index, frame.timestamp_ns, frame.mask)


def test_service_shows_each_cameras_quality_and_notes_several_people(tmp_path, rendered):
    """Agents report person-sized candidates per frame and their quality figures; the rig
    summary shows each camera's latest, and windows in which c0 saw two people say so
    (the tracked walker is still the one estimated)."""
    cameras = {**rendered, "c0": [_with_bystander(f) for f in rendered["c0"]]}
    # max_wait_ms as in test_agents_stream_windows_estimated_published_and_served: a c0 frame that came
    # more than the default 120 ms after c1's (CI's two cores, once) was left out of its frame set, and the
    # window counted 9 crowded frames of 10; the frames' latency budget is not what is tested here.
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=False, max_wait_ms=400.0, live_rig=False)
    with ServerThread(settings) as srv:
        stats = _run_agents(settings.zenoh_listen[0], cameras, quality_every=1)
        rig = wait_for(lambda: (r := srv.rig(RIG)) and r["windows"]["estimated"] >= 3 and r,
                       timeout=20, what="three estimated windows")
        est = srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": 0}).json()["estimates"]
    assert rig["cameras"]["c0"]["n_candidates"] == 2 and rig["cameras"]["c1"]["n_candidates"] == 1
    for cam, st in stats.items():  # the last message's figures, exactly as the agent computed them
        assert rig["cameras"][cam]["quality"] == dataclasses.asdict(st.quality()), cam
        assert rig["cameras"][cam]["quality"]["walker_fraction"] > 0.9
    several = "several people in view in"
    for e in est:
        crowded = sum(i >= BYSTANDER for i in range(e["window"]["first_index"], e["window"]["last_index"] + 1))
        notes = [n for n in e["cameras"]["c0"]["notes"] if n.startswith(several)]
        assert notes == [f"{several} {crowded} of 20 frames (up to 2): the papers assume one walker "
                         "per rig: the tracked one is kept"], (e["window"], e["cameras"]["c0"]["notes"])
        assert not any(several in n for n in e["cameras"]["c1"]["notes"])
    az, _ = TRUTH["c0"]  # the bystander did not take the walker's place
    assert abs((est[-1]["smoothed"]["c0"]["azimuth_deg"] - az + 180) % 360 - 180) < 45


def _sent(cam: str, index: int, mask: np.ndarray, track_id: int) -> SilhouetteMessage:
    """An agent's message for ``mask`` (a full-frame boolean silhouette) on its track ``track_id``."""
    x, y, w, h = cv2.boundingRect(mask.astype(np.uint8))
    return dataclasses.replace(_msg(cam, index), rig=RIG, box=Box(x, y, w, h), image_size=mask.shape[::-1],
                               mask=np.where(mask[y:y + h, x:x + w], 255, 0).astype(np.uint8), track_id=track_id)


def test_frames_before_an_agents_move_onto_the_walker_are_left_out(tmp_path, rendered):
    """c0's agent followed someone else for the window's first 10 frames (here: a walker seen from c1's side,
    180 deg round) and its look back then moved the track onto the walker (track_id 0 -> 1): the window
    estimates c0 from the walker's 10 frames only, and says which it left out."""
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=False, max_wait_ms=400.0, live_rig=False)
    walk = {cam: [f.mask for f in frames[EMPTY:EMPTY + 20]] for cam, frames in rendered.items()}
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=[settings.zenoh_listen[0]])) as session:
        for k in range(20):
            moved = k >= 10
            session.put(f"posecal/{RIG}/c0/silhouette",
                        encode(_sent("c0", k, walk["c0" if moved else "c1"][k], int(moved))))
            session.put(f"posecal/{RIG}/c1/silhouette", encode(_sent("c1", k, walk["c1"][k], 0)))
            time.sleep(0.02)
        wait_for(lambda: srv.rig(RIG).get("windows", {}).get("estimated", 0) >= 1, timeout=30,
                 what="the window estimated")
        est = srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": 0}).json()["estimates"][0]
    assert est["window"]["other_person"] == {"c0": list(range(10))}
    for cam, (az, _) in TRUTH.items():
        assert abs((est["cameras"][cam]["azimuth_deg"] - az + 180) % 360 - 180) < 30, (cam, est["cameras"][cam])
    LiveEstimate.model_validate(est)


def test_a_window_published_before_a_late_move_is_estimated_again(tmp_path, rendered):
    """c0's agent followed the walker for 10 frames, then someone else (a walker seen from c1's side, 180 deg
    round), and its look back moved the track back onto the walker only at frame 25, saying the old track was
    off them from frame 10 (track_from): the first window (frames 0-19), estimated before the move, is
    estimated again without c0's frames 10-19, published again (window.revision 1) and replaces the first
    estimate in the history; the later windows leave out the frames 10-24 as they are estimated."""
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=False, max_wait_ms=400.0, live_rig=False)
    walk = {cam: [f.mask for f in frames[EMPTY:EMPTY + 40]] for cam, frames in rendered.items()}
    heard = []
    with ServerThread(settings) as srv, zenoh.open(build_config(connect=[settings.zenoh_listen[0]])) as session:
        sub = session.declare_subscriber(f"posecal/{RIG}/estimate", lambda s: heard.append(json.loads(bytes(
            s.payload.to_bytes()))))

        def send(k):
            moved, away = k >= 25, 10 <= k < 25
            c0 = dataclasses.replace(_sent("c0", k, walk["c1" if away else "c0"][k], int(moved)),
                                     track_from=10 if moved else None)
            session.put(f"posecal/{RIG}/c0/silhouette", encode(c0))
            session.put(f"posecal/{RIG}/c1/silhouette", encode(_sent("c1", k, walk["c1"][k], 0)))
            time.sleep(0.02)

        for k in range(25):
            send(k)
        first = wait_for(lambda: srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": 0}).json()[
            "estimates"], timeout=30, what="the first window estimated")[0]
        for k in range(25, 40):
            send(k)
        wait_for(lambda: srv.rig(RIG).get("windows", {}).get("revised", 0) >= 1
                 and srv.rig(RIG)["windows"]["estimated"] >= 3, timeout=30, what="the first window revised")
        est = srv.client.get(f"/v1/rigs/{RIG}/estimates", params={"since": 0}).json()["estimates"]
        polled = srv.client.get(f"/v1/rigs/{RIG}/estimates",
                                params={"updated_since": first["window"]["update"]}).json()
        sub.undeclare()
    assert first["window"]["seq"] == 1 and first["window"]["revision"] == 0 and first["window"]["other_person"] == {}
    assert [e["window"]["seq"] for e in est] == [1, 2, 3]  # replaced in place, in window order
    # polled by update: everything kept after the first estimate, the revision too, in the order kept
    assert sorted((e["window"]["seq"], e["window"]["revision"]) for e in polled["estimates"]) == [(1, 1), (2, 0), (3, 0)]
    updates = [e["window"]["update"] for e in polled["estimates"]]
    assert updates == sorted(updates) and polled["next_updated_since"] == updates[-1] == 4
    revised = est[0]
    assert revised["window"]["revision"] == 1 and revised["window"]["other_person"] == {"c0": list(range(10, 20))}
    assert est[1]["window"]["other_person"] == {"c0": list(range(10, 25))}
    assert est[2]["window"]["other_person"] == {"c0": list(range(20, 25))}
    assert [h["window"]["revision"] for h in heard if h["window"]["seq"] == 1] == [0, 1]  # published again
    def off(e, cam):
        return abs((e["cameras"][cam]["azimuth_deg"] - TRUTH[cam][0] + 180) % 360 - 180)

    assert off(first, "c0") > 45  # the first estimate matched c0 on both people (91 deg off when written)
    for cam in TRUTH:
        assert off(revised, cam) < 30, (cam, revised["cameras"])
    LiveEstimate.model_validate(revised)


def test_the_live_rig_is_calibrated_from_the_keypoints_the_agents_send(tmp_path, rendered):
    """Agents that send a detector's keypoints with their silhouettes (here the renders' joints with a
    pixel of noise): the live rig is calibrated from them, on every frame of the windows (no posture
    measured), and within a few degrees of the truth where the postures' rig is only rough (below)."""
    from estimator._selfcal_core import geodesic_deg
    from estimator.joints import N_JOINTS
    from estimator.rig import rotations_from_viewpoints

    rng = np.random.default_rng(0)
    keypoints = {}
    for cam, (az, el) in TRUTH.items():  # the same walk and cameras as ``rendered``
        src = SyntheticSource.from_spec(f"seed=3,azimuth={az},elevation={el},fps=15,empty={EMPTY},"
                                        f"pass={WALK},gap=0")
        keypoints[cam] = {i: src.camera.project(t["joints"][:N_JOINTS]) + rng.normal(0.0, 1.0, (N_JOINTS, 2))
                          for i in range(EMPTY + WALK) if (t := src.truth(i)) is not None}
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=False, max_wait_ms=400.0, live_rig_every=1)
    with ServerThread(settings) as srv:
        _run_agents(settings.zenoh_listen[0], rendered, keypoints)
        cal = wait_for(lambda: (r := srv.client.get(f"/v1/rigs/{RIG}/calibration")).status_code == 200
                       and (c := r.json())["frames"] >= 40 and c,
                       timeout=90, what="a calibration on 40 frames")
    LiveCalibration.model_validate(cal)
    assert cal["postures"] == "keypoints" and cal["source"] == "self-calibration", cal["notes"]
    assert any("detector's keypoints" in n for n in cal["notes"]), cal["notes"]
    r = np.array(cal["calibration"]["cameras"]["c1"]["rotation"])
    truth = rotations_from_viewpoints([TRUTH["c0"], TRUTH["c1"]])[1]
    # Two cameras facing each other 10 m away: little perspective, so focal length and tilt trade off
    # (1.9 deg here; the posture's rig, next test, is only asked to be within 30)
    assert geodesic_deg(r, truth) < 2.5, (geodesic_deg(r, truth), cal["notes"])


def test_the_live_rig_is_calibrated_from_a_few_postures_per_window(tmp_path, rendered):
    """GET /v1/rigs/{rig}/calibration: the rig from the mNBP postures of 6 frames per window,
    recalibrated after every window, in its own low-priority process; the viewpoints go on. Its
    pinhole cameras are logged to Rerun (the frusta beside the viewpoints' cameras), and so is the
    person's newest posture, which the calibration answers too."""
    from rerun.chunk import RrdReader

    from estimator._selfcal_core import geodesic_deg
    from estimator.rig import rotations_from_viewpoints

    rrd = tmp_path / "live.rrd"
    settings = make_settings(tmp_path, live=True, job_workers=0, window_length=20, window_hop=10,
                             feedback=False, max_wait_ms=400.0, live_rig_frames=6, live_rig_every=1,
                             rerun=f"save:{rrd}")
    with ServerThread(settings) as srv:
        assert srv.client.get(f"/v1/rigs/{RIG}/calibration").status_code == 404  # no such rig yet
        _run_agents(settings.zenoh_listen[0], rendered)
        rig = wait_for(lambda: (r := srv.rig(RIG)) and r["windows"]["estimated"] >= 3 and r,
                       timeout=20, what="three estimated windows")
        # Windows that come while one is measured supersede each other: at least two are measured.
        cal = wait_for(lambda: (r := srv.client.get(f"/v1/rigs/{RIG}/calibration")).status_code == 200
                       and (c := r.json())["frames"] >= 8 and c,
                       timeout=90, what="a calibration on 8 frames")
        # Each window estimated after it carries the person's posture from the live rig, and how far it lags
        # (the cameras stream the walk again: the agents restart, their frames are realigned onto the rig).
        _run_agents(settings.zenoh_listen[0], rendered)
        carried = wait_for(lambda: (e := srv.client.get(f"/v1/rigs/{RIG}/estimate").json()).get("person") and e,
                           timeout=30, what="a window carrying the person's posture")
        metrics = srv.client.get("/metrics").text
    person = carried["person"]
    assert person["lag_windows"] == carried["window"]["seq"] - person["window_seq"] >= 0
    assert person["frame_index"] <= carried["window"]["last_index"] and np.shape(person["joints3d"]) == (13, 3)
    LiveEstimate.model_validate(carried)  # as documented
    assert cal["rig"] == RIG and cal["frames"] >= 8 and 0 <= cal["lag_windows"] <= rig["windows"]["estimated"]
    assert cal["source"] == "self-calibration" and cal["postures"] == "mnbp", cal["notes"]
    r = np.array(cal["calibration"]["cameras"]["c1"]["rotation"])
    truth = rotations_from_viewpoints([TRUTH["c0"], TRUTH["c1"]])[1]
    # The cameras face each other (180 deg apart); the small test model and a dozen frames of postures
    # give a rough rig: within 30 deg, not swapped or mirrored.
    assert geodesic_deg(r, truth) < 30.0, (geodesic_deg(r, truth), cal["notes"])
    assert cal["body"]["stature_m"] == 1.75
    assert "posecal_live_rig_seconds_count" in metrics
    assert cal["calibration"]["cameras"]["c1"]["focal_px"] > 0  # pinhole cameras, hence frusta
    # the person's newest posture: 13 joints in the person frame, metres, standing upright
    person = np.array(cal["person"]["joints3d"])
    assert person.shape == (13, 3) and np.isfinite(person).all()
    assert cal["person"]["frame_index"] <= cal["last_index"]
    assert 1.2 < person[:, 2].max() - person[:, 2].min() < 2.0, person  # head over ankles, at 1.75 m
    assert abs(person[:, 2].mean()) < 0.3  # centred on the joints' centroid
    paths = {c.entity_path.lstrip("/") for c in RrdReader(rrd).stream()}
    for cam in ("c0", "c1"):
        assert f"rigs/{RIG}/world/rig/{cam}" in paths, sorted(p for p in paths if "/world/" in p)
    assert f"rigs/{RIG}/world/person" in paths  # beside the model's skeleton


def test_window_results_are_kept_in_window_order():
    """Two live workers may finish window 3 before window 2: the history stays in seq order,
    bounded, and a result older than a full history is not kept."""
    import collections

    from service.live import insert_by_seq

    recent = collections.deque(maxlen=3)
    for seq in (1, 3, 2, 5, 4):
        insert_by_seq(recent, {"window": {"seq": seq}})
    assert [r["window"]["seq"] for r in recent] == [3, 4, 5]
    insert_by_seq(recent, {"window": {"seq": 2}})  # older than all kept
    assert [r["window"]["seq"] for r in recent] == [3, 4, 5]
