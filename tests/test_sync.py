"""Offline synchronisation of recorded videos (issue 19): estimator.sync, posecal sync, estimate --sync,
and jobs on videos that were not started together."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimator.hmm import PhaseHMM
from estimator.pipeline import CameraTrack, tracks_from_sequence
from estimator.sync import (CameraClock, SyncConfig, SyncResult, align_tracks, camera_clock, synchronize,
                            timeline_frames)
from estimator.synth import SynthSpec, synthesize, synthesize_recordings
from service.cli import main

RATES = np.array([15.0, 25.0, 30.0])
MOCAP = Path(__file__).resolve().parents[2] / "shared" / "data" / "mocap"


def _clocks(starts, seconds: float = 5.0) -> dict[str, np.ndarray]:
    return {f"c{i}": starts[i] + np.arange(int(seconds * RATES[i])) / RATES[i] for i in range(3)}


def _errors_frames(result: SyncResult, starts) -> dict[str, float]:
    ref = int(result.reference[1:])
    return {c: (off - (starts[int(c[1:])] - starts[ref])) * result.fps[c] for c, off in result.offsets_s.items()}


# ------------------------------------------------------------------ the pieces


def test_the_phase_hmm_at_another_frame_rate_keeps_the_advance_per_second():
    base = PhaseHMM()
    assert PhaseHMM().at_fps(15.0).probs == base.probs
    for fps in (10.0, 25.0, 30.0):
        hmm = base.at_fps(fps)
        assert hmm.mean_advance * fps == pytest.approx(base.mean_advance * 15.0)
        assert np.allclose(hmm.transmat_.sum(axis=1), 1.0)
    with pytest.raises(ValueError):
        base.at_fps(0.0)


def test_a_varying_pace_changes_the_phase_rate_and_nothing_else():
    even = synthesize(SynthSpec(n_frames=6, seed=4))
    again = synthesize(SynthSpec(n_frames=6, seed=4, cadence_variation=0.0))
    assert [f["phase"] for f in even.truth["frames"]] == [f["phase"] for f in again.truth["frames"]]
    t = np.arange(0, 8, 1 / 15)
    recs = synthesize_recordings(SynthSpec(n_cameras=1, seed=4, cadence_variation=0.2, image_size=(160, 120)),
                                 {"c0": t})
    phase = np.unwrap(2 * np.pi * np.array([f["phase"] for f in recs["c0"].truth["frames"]])) / (2 * np.pi)
    rate = np.diff(phase) * 15
    assert rate.max() / rate.min() > 1.2  # the cadence moves by ±20 %
    assert recs["c0"].truth["clock"] == {"start_s": 0.0, "fps": pytest.approx(15.0)}


def _clock(t0: float, fps: float, seconds: float, pace) -> CameraClock:
    """A camera seeing the walker whose unwrapped phase at walk time ``s`` is ``pace(s)``, starting at ``t0``."""
    times = np.arange(int(seconds * fps)) / fps
    phase = pace(times + t0)
    return CameraClock(times, phase, fps)


def test_offsets_are_exact_on_clean_phases_and_an_even_pace_is_flagged():
    varying = lambda s: s + 0.15 * np.sin(2 * np.pi * s / 3.7)  # noqa: E731  cycles: ±15 % pace changes
    clocks = {"a": _clock(0.3, 15, 6, varying), "b": _clock(1.0, 30, 6, varying), "c": _clock(0.0, 25, 6, varying)}
    res = synchronize(clocks, SyncConfig(reference="a"))
    assert res.offsets_s["b"] == pytest.approx(0.7, abs=0.003) and res.offsets_s["c"] == pytest.approx(-0.3, abs=0.003)
    assert not any(res.ambiguous.values()) and res.notes == []
    # At an even pace a whole cycle later fits as well: the result says so rather than guessing silently.
    even = lambda s: 1.05 * s  # noqa: E731
    res = synchronize({"a": _clock(0.3, 15, 6, even), "b": _clock(1.0, 30, 6, even)}, SyncConfig(reference="a"))
    assert res.ambiguous["b"] and "too even" in res.notes[0]
    # A camera too slow to follow the gait is never trusted.
    res = synchronize({"a": _clock(0.0, 15, 6, varying), "b": _clock(0.5, 5, 6, varying)}, SyncConfig(reference="a"))
    assert res.ambiguous["b"] and any("5 fps" in n for n in res.notes)


def test_synchronize_refuses_what_it_cannot_use():
    pace = lambda s: s  # noqa: E731
    with pytest.raises(ValueError, match="two or more"):
        synchronize({"a": _clock(0, 15, 4, pace)})
    blind = CameraClock(np.arange(30) / 15, np.full(30, np.nan), 15.0)
    with pytest.raises(ValueError, match="not seen"):
        synchronize({"a": _clock(0, 15, 4, pace), "b": blind})
    with pytest.raises(ValueError, match="reference"):
        synchronize({"a": _clock(0, 15, 4, pace), "b": _clock(0, 15, 4, pace)}, SyncConfig(reference="x"))
    # Recordings too short to share min_overlap_s at any offset: not synchronised, and said.
    res = synchronize({"a": _clock(0, 15, 1.5, pace), "b": _clock(0, 15, 1.5, pace)}, SyncConfig(reference="a"))
    assert np.isnan(res.offsets_s["b"]) and "not synchronised" in res.notes[0]
    assert res.to_dict()["cameras"]["b"]["offset_s"] is None


def test_align_tracks_pairs_frames_by_time():
    sil = np.ones((4, 2), np.uint8)

    def track(n):
        return CameraTrack([sil] * n, np.tile([0.0, 0.0, 2.0, 4.0], (n, 1)))

    tracks = {"a": track(15), "b": track(60)}  # 1 s at 15 fps; 2 s at 30 fps starting 0.5 s earlier
    sync = SyncResult("a", {"a": 0.0, "b": -0.5}, {"a": 15.0, "b": 30.0}, {"a": 0.0, "b": 0.0},
                      {"a": np.inf, "b": 1.0}, {"a": False, "b": False})
    aligned, times = align_tracks(tracks, sync)
    assert times[0] == pytest.approx(-0.5) and np.diff(times) == pytest.approx(np.full(len(times) - 1, 1 / 15))
    a = [s is not None for s in aligned["a"].silhouettes]
    b = [s is not None for s in aligned["b"].silhouettes]
    assert len(a) == len(b) == len(times)
    assert not any(a[:7]) and all(a[8:22])  # "a" starts at 0 s: timeline frame 7.5 -> its first frame at 8
    assert all(b) and len(times) == 30  # b covers the whole timeline (-0.5 .. 1.5 s)
    assert np.isnan(aligned["a"].boxes[0]).all() and not np.isnan(aligned["a"].boxes[10]).any()


# ------------------------------------------------------------ on rendered walks


@pytest.fixture(scope="module")
def small(small_model_path):
    from estimator.appearance import load_model

    return load_model(small_model_path)


@pytest.mark.parametrize("seed", [1, 2])
def test_offsets_of_cameras_at_different_rates_are_found_to_a_fraction_of_a_frame(small, seed):
    starts = np.array([0.0, 1.2, 0.5]) + 0.1 * seed
    recs = synthesize_recordings(SynthSpec(n_cameras=3, seed=seed, cadence_variation=0.1, image_size=(640, 360)),
                                 _clocks(starts))
    clocks = {c: camera_clock(tracks_from_sequence(s)[c], small, s.fps) for c, s in recs.items()}
    res = synchronize(clocks)
    errors = _errors_frames(res, starts)
    assert all(abs(e) < 0.5 for e in errors.values()), errors
    assert not any(res.ambiguous.values()), res.notes
    assert all(0 < u < 0.5 / res.fps[c] for c, u in res.uncertainty_s.items() if c != res.reference)


@pytest.fixture(scope="module")
def unsynced_videos(tmp_path_factory):
    """Three videos of one walk at 15, 25 and 30 fps, started 0, 1.3 and 0.6 s into it."""
    from capture.synthetic import write_recording

    starts = np.array([0.0, 1.3, 0.6])
    recs = synthesize_recordings(SynthSpec(n_cameras=3, seed=2, cadence_variation=0.1, image_size=(480, 270)),
                                 _clocks(starts, seconds=6.0))
    folder = tmp_path_factory.mktemp("unsynced")
    for i, (cam, rec) in enumerate(recs.items()):
        write_recording(str(folder / f"{cam}.avi"), rec.silhouettes[cam], rec.fps, seed=i, empty=int(rec.fps))
    return folder, starts


def test_posecal_sync_finds_the_offsets_of_videos(unsynced_videos, small_model_path, tmp_path, capsys):
    folder, starts = unsynced_videos
    out = tmp_path / "sync.json"
    assert main(["sync", str(folder), "--model", str(small_model_path), "--out", str(out)]) == 0
    res = json.loads(out.read_text())
    ref = int(res["reference"][1:])
    for cam, v in res["cameras"].items():
        true = starts[int(cam[1:])] - starts[ref]
        assert abs(v["offset_s"] - true) * v["fps"] < 0.5, (cam, v, true)
        assert v["fps"] == pytest.approx(RATES[int(cam[1:])])
    err = capsys.readouterr().err
    assert "frames at 25 fps" in err
    # Usage and input errors: exit 2 with the reason.
    assert main(["sync", str(folder / "c0.avi"), "--model", str(small_model_path)]) == 2
    assert "not a folder of videos" in capsys.readouterr().err
    assert main(["sync", str(folder), "--reference", "c9", "--model", str(small_model_path)]) == 2
    assert "c9" in capsys.readouterr().err
    assert main(["sync", str(folder), "--max-offset", "-1"]) == 2


def test_estimate_on_unsynchronized_videos_pairs_frames_by_time(unsynced_videos, small_model_path, tmp_path):
    folder, starts = unsynced_videos
    out = tmp_path / "r.json"
    assert main(["estimate", str(folder), "--model", str(small_model_path), "--posture", "model",
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    sync = result["sync"]
    assert result["sequence"]["fps"] == pytest.approx(15.0)  # the slowest camera's rate: no frame used twice
    ref = int(sync["reference"][1:])
    for cam, v in sync["cameras"].items():
        assert abs(v["offset_s"] - (starts[int(cam[1:])] - starts[ref])) * v["fps"] < 0.5
    # On the timeline all three see the walker only where their recordings overlap (and he is in view).
    both = [f for f in result["frames"] if len(f["seen_by"]) == 3]
    assert len(both) >= 45
    off = tmp_path / "off.json"
    assert main(["estimate", str(folder), "--model", str(small_model_path), "--posture", "model", "--sync", "off",
                 "--out", str(off)]) == 0
    assert "sync" not in json.loads(off.read_text())


def test_a_job_on_unsynchronized_videos_is_synchronized(unsynced_videos, small_model_path, tmp_path):
    """REST: videos uploaded as they were recorded; the job finds the offsets (sync "auto", the default)."""
    from conftest_service import ServerThread, make_settings, wait_for

    folder, starts = unsynced_videos
    files = [("files", (p.name, p.read_bytes(), "video/x-msvideo")) for p in sorted(folder.glob("*.avi"))]
    with ServerThread(make_settings(tmp_path)) as srv:
        ids = [srv.client.post("/v1/jobs", files=files, data={"posture": "model", **extra}).json()["id"]
               for extra in ({}, {"sync": "off"})]
        assert srv.client.post("/v1/jobs", files=files, data={"sync": "sometimes"}).status_code == 422
        done = [wait_for(lambda i=i: (j := srv.client.get(f"/v1/jobs/{i}").json())["state"] in ("done", "failed")
                         and j, timeout=120, what=f"job {i}") for i in ids]
        assert [d["state"] for d in done] == ["done", "done"], done
        synced, by_index = (srv.client.get(f"/v1/jobs/{i}/result").json() for i in ids)
    ref = int(synced["sync"]["reference"][1:])
    for cam, v in synced["sync"]["cameras"].items():
        assert abs(v["offset_s"] - (starts[int(cam[1:])] - starts[ref])) * v["fps"] < 0.5
    assert synced["fps"] == pytest.approx(15.0) and "sync" not in by_index
    # Paired by time, the three cameras see the walker together over the overlap of their recordings.
    assert sum(len(f["seen_by"]) == 3 for f in synced["frames"]) >= 45


def test_a_hint_settles_the_whole_cycle_at_an_even_pace():
    even = lambda s: 1.05 * s  # noqa: E731
    clocks = {"a": _clock(0.3, 15, 6, even), "b": _clock(1.3, 30, 6, even)}
    res = synchronize(clocks, SyncConfig(reference="a", hints={"b": 0.9}))  # a clap heard 0.1 s off
    assert res.offsets_s["b"] == pytest.approx(1.0, abs=0.003) and not res.ambiguous["b"]
    with pytest.raises(ValueError, match="unknown camera"):
        synchronize(clocks, SyncConfig(hints={"z": 1.0}))
    assert main(["sync", "a", "b", "--hint", "c1"]) == 2


def test_a_short_recording_of_a_rig_started_together_stays_paired_by_index(small):
    """Three equal 3 s videos of a CMU walk from a synchronised rig: the walk alone fits half a cycle
    later about as well (the old rule moved two cameras by 9 frames); equal rate and length keep the
    index pairing. A real 4-frame offset between equal-length clips is still found."""
    from estimator.mocap import read_motion
    from estimator.sync import sync_tracks

    motion = read_motion(MOCAP / "16_15.bvh")
    tracks = tracks_from_sequence(synthesize(SynthSpec(n_cameras=3, n_frames=45, seed=0, image_size=(320, 240)),
                                             motion=motion))
    rates = {c: 15.0 for c in tracks}
    before = SyncConfig(together_margin=SyncConfig().min_margin)  # the rule before
    _, _, old, _ = sync_tracks(tracks, rates, small, config=before)
    assert max(abs(o) for o in old.offsets_frames().values()) > 4
    _, _, res, _ = sync_tracks(tracks, rates, small)
    assert all(o == 0.0 for o in res.offsets_s.values())
    assert "same frame rate and length" in res.notes[-1]
    late = {c: CameraTrack(t.silhouettes[4:] if c == "c1" else t.silhouettes[:41],
                           t.boxes[4:] if c == "c1" else t.boxes[:41], t.full_frame, t.image_size)
            for c, t in tracks.items()}
    _, _, res, _ = sync_tracks(late, rates, small)
    # Not imposed: the walk's own answer (the small model's is half a cycle off, -4.9 frames, its own
    # ambiguity on a 2.7 s walk; the shipped model finds 4 +- 0.5 on such clips, docs/SYNC.md).
    assert abs(res.offsets_frames()["c1"]) > 3 and not any("kept" in n for n in res.notes)


def test_cameras_started_together_whose_clocks_disagree_stay_paired_by_index(small):
    """Equal 3 s videos of a synchronised rig where one camera's walk reads 25 % faster than the
    others' (its frames taken 1.25 apart, as a spoiled phase track reads): no offset found from a clock
    that disagrees can be trusted, so the index pairing stands, and the note says why."""
    from estimator.mocap import read_motion
    from estimator.sync import sync_tracks

    motion = read_motion(MOCAP / "16_15.bvh")
    full = tracks_from_sequence(synthesize(SynthSpec(n_cameras=3, n_frames=57, seed=0, image_size=(320, 240)),
                                           motion=motion))
    fast = np.rint(np.arange(45) * 1.25).astype(int)
    tracks = {c: CameraTrack([t.silhouettes[k] for k in (fast if c == "c1" else range(45))],
                             np.asarray(t.boxes)[fast if c == "c1" else np.arange(45)], t.full_frame, t.image_size)
              for c, t in full.items()}
    rates = {c: 15.0 for c in tracks}
    trusting = SyncConfig(together_cadence=np.inf, together_margin=SyncConfig().min_margin)
    _, _, moved, _ = sync_tracks(tracks, rates, small, config=trusting)
    assert max(abs(o) for o in moved.offsets_frames().values()) > 1  # the walk alone moves a camera
    # The equal-length rule's margin at the general one, so that only the cadence rule can keep the pairing.
    _, _, res, _ = sync_tracks(tracks, rates, small, config=SyncConfig(together_margin=SyncConfig().min_margin))
    assert all(o == 0.0 for o in res.offsets_s.values())
    assert "disagree on the cadence" in res.notes[-1], res.notes


def test_a_detectors_keypoints_follow_their_video_onto_the_timeline():
    """Keypoints are numbered by each video's own frames; put on the common timeline through the same
    frame indices as the silhouettes (``timeline_frames``), frame i of the timeline holds, per camera,
    the keypoints of the video frame shown there: here b started 0.4 s after a and runs at 30 fps."""
    from service.keypoints_io import Keypoints, keypoints_on_timeline

    sync = SyncResult("a", {"a": 0.0, "b": 0.4}, {"a": 15.0, "b": 30.0}, {"a": 0.0, "b": 0.0},
                      {"a": np.inf, "b": 1.0}, {"a": False, "b": False})
    frames, times = timeline_frames({"a": 30, "b": 60}, sync)
    assert len(times) == 36 and times[0] == 0.0  # 0 .. 2.33 s at 15 fps (b ends at 0.4 + 59/30 s)
    assert frames["a"][:3].tolist() == [0, 1, 2] and frames["a"][30:].tolist() == [-1] * 6
    assert frames["b"][:6].tolist() == [-1] * 6 and frames["b"][6:9].tolist() == [0, 2, 4]
    # Each camera's keypoints carry their own frame number in x, so where they landed shows.
    own = np.arange(60, dtype=float)[None, :, None, None] * np.array([1.0, 0.0])
    kp = Keypoints(["a", "b"], np.broadcast_to(own, (2, 60, 13, 2)).copy(), np.ones((2, 60, 13)),
                   list(range(60)), {"a": "BODY_25", "b": "BODY_25"}, "openpose")
    on = keypoints_on_timeline(kp, frames)
    assert on["a"].shape == on["b"].shape == (36, 13, 2)
    np.testing.assert_array_equal(on["a"][:30, 0, 0], np.arange(30))
    assert np.isnan(on["a"][30:]).all() and np.isnan(on["b"][:6]).all()
    np.testing.assert_array_equal(on["b"][6:, 0, 0], 2 * np.arange(30))
    tracks = {c: CameraTrack([np.full((4, 2), 255, np.uint8)] * n, np.tile([0.0, 0, 2, 4], (n, 1)), True, (64, 48))
              for c, n in (("a", 30), ("b", 60))}
    aligned, _ = align_tracks(tracks, sync)  # the silhouettes took the same frames
    assert [s is None for s in aligned["b"].silhouettes] == (frames["b"] < 0).tolist()


def test_keypoints_of_videos_started_apart_land_on_the_frames_their_silhouettes_do(unsynced_videos, small):
    """Three videos started 0, 1.3 and 0.6 s into a walk, at 15, 25 and 30 fps, synchronised from the walk
    (``sync_videos``, as jobs and ``posecal estimate`` do): at every frame of the timeline each camera's
    silhouette and its keypoints come from the same frame of its own video."""
    from service.keypoints_io import Keypoints, keypoints_on_timeline
    from service.worker import sync_videos, video_tracks

    folder, starts = unsynced_videos
    tracks, rates, _ = video_tracks(folder, warmup=None, report=lambda f, s: None)
    aligned, fps, sync, frames = sync_videos(tracks, rates, small, "auto")
    assert fps == pytest.approx(15.0) and set(frames) == set(tracks) == set(aligned)
    for c, k in frames.items():
        assert len(k) == len(aligned[c].silhouettes) and k.max() < len(tracks[c].silhouettes)
        assert all(s is (tracks[c].silhouettes[j] if j >= 0 else None) for s, j in zip(aligned[c].silhouettes, k))
    late = max(frames, key=lambda c: starts[int(c[1:])])  # c1, started 1.3 s after c0: nothing early on
    assert (frames[late][:15] < 0).all() and frames[late][25] >= 0
    # Keypoints numbered by each video's own frames, carrying that number in x.
    n = max(len(t.silhouettes) for t in tracks.values())
    names = sorted(tracks)
    own = np.broadcast_to(np.arange(n, dtype=float)[None, :, None, None] * np.array([1.0, 0.0]), (3, n, 13, 2))
    kp = Keypoints(names, own.copy(), np.ones((3, n, 13)), list(range(n)), {c: "BODY_25" for c in names}, "openpose")
    on = keypoints_on_timeline(kp, frames)
    for c, k in frames.items():
        np.testing.assert_array_equal(on[c][k >= 0, 0, 0], k[k >= 0])
        assert np.isnan(on[c][k < 0]).all()
    with pytest.raises(ValueError, match="no camera has a frame"):
        keypoints_on_timeline(kp, {c: np.full(4, -1) for c in names})


def test_index_frames_pair_by_index_and_mark_a_shorter_camera_past_its_end():
    from estimator.sync import index_frames

    frames = index_frames({"a": 3, "b": 5})
    assert frames["a"].tolist() == [0, 1, 2, -1, -1] and frames["b"].tolist() == [0, 1, 2, 3, 4]
