"""Walking pose and viewpoints from silhouettes: the pipeline and `posecal estimate`."""

import dataclasses
import json
import os
import shutil

import numpy as np
import pytest

from estimator.pipeline import CameraTrack, EstimateConfig, estimate_walk, tracks_from_sequence
from estimator.sequence import write_sequence
from estimator.skeleton import BodyShape
from estimator.synth import SynthSpec, synthesize
from service.cli import main


def az_error(a, b):
    return abs((a - b + 180.0) % 360.0 - 180.0)


def phase_error(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 0.5) % 1.0 - 0.5)


@pytest.fixture(scope="module")
def sequences():
    return [
        synthesize(SynthSpec(n_cameras=2, n_frames=30, seed=s, elevations=(0.0, 15.0), image_size=(320, 240)))
        for s in range(4)
    ]


@pytest.mark.parametrize("method, az_tol, phase_ok", [("exemplars", 5.0, 0.95), ("paper", 8.0, 0.55)])
def test_estimate_close_to_truth(small_model, sequences, method, az_tol, phase_ok):
    az_err, ph_err = [], []
    for seq in sequences:
        est = estimate_walk(tracks_from_sequence(seq), small_model, config=EstimateConfig(method=method))
        truth = seq.truth
        for cam in seq.cameras:
            az_err.append(az_error(est.cameras[cam].viewpoint.azimuth_deg, truth["cameras"][cam]["azimuth_deg"]))
        ph_err.append(phase_error(est.phase, [f["phase"] for f in truth["frames"]]))
        assert est.joints3d.shape == (30, 13, 3)
        np.testing.assert_allclose(est.joints3d.mean(axis=1), 0.0, atol=1e-9)
    ph_err = np.concatenate(ph_err)
    # A coarse test model (15-degree grid, 40 clusters); the evaluation measures the real one.
    # Measured here (8 bodies taking turns): exemplars 1.2 deg median, 100% of frames within
    # 0.1 cycle; paper 2.9 deg, 62% (with one body: 2.2 deg, 100%; 3.6 deg, 79%).
    assert np.median(az_err) < az_tol, az_err
    assert np.mean(ph_err <= 0.1) > phase_ok, np.mean(ph_err <= 0.1)


def test_joints2d_lie_on_the_silhouettes(small_model, sequences):
    seq = sequences[0]
    est = estimate_walk(tracks_from_sequence(seq), small_model)
    for cam in seq.cameras:
        j = est.cameras[cam].joints2d
        inside = []
        for t, sil in enumerate(seq.silhouettes[cam]):
            uv = np.round(j[t]).astype(int)
            ok = (uv[:, 0] >= 0) & (uv[:, 0] < sil.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < sil.shape[0])
            dil = sil > 0
            inside.append(np.mean(dil[uv[ok, 1], uv[ok, 0]]) if ok.any() else 0.0)
        assert np.mean(inside) > 0.6, (cam, np.mean(inside))


def test_missing_frames_and_one_camera(small_model, sequences):
    seq = sequences[1]
    tracks = tracks_from_sequence(seq)
    t0 = tracks["c0"]
    for k in (3, 4, 5, 17):
        t0.silhouettes[k] = None
        t0.boxes[k] = np.nan
    est = estimate_walk(tracks, small_model)
    result = est.to_result()
    assert result["frames"][4]["observed_phase"]["c0"] is None
    assert "c0" not in result["frames"][4]["joints2d"] and "c1" in result["frames"][4]["joints2d"]
    assert len(result["frames"]) == 30  # nothing invented, nothing dropped
    # Honest per-frame output: who saw each frame, and how sure the phase is.
    assert result["frames"][4]["seen_by"] == ["c1"] and result["frames"][0]["seen_by"] == ["c0", "c1"]
    assert not any(f["predicted"] for f in result["frames"])
    for f in result["frames"]:
        assert len(f["phase_posterior"]) == 20 and abs(sum(f["phase_posterior"]) - 1.0) < 1e-3
        assert 0.0 <= f["phase_confidence"] <= 1.0
    assert result["schema_version"] == 1 and result["units"]["joints3d"] == "m"
    # Frames no camera saw: predicted by the HMM, and less sure than the frames around them.
    t1 = tracks["c1"]
    for k in (3, 4, 5):
        t1.silhouettes[k] = None
        t1.boxes[k] = np.nan
    gap = estimate_walk(tracks, small_model).to_result()["frames"]
    assert [f["index"] for f in gap if f["predicted"]] == [3, 4, 5]
    assert gap[4]["seen_by"] == [] and gap[4]["phase"] is not None
    seen = [f["phase_confidence"] for f in gap if not f["predicted"]]
    assert gap[4]["phase_confidence"] < np.median(seen)
    one = estimate_walk({"c1": tracks["c1"]}, small_model)
    assert az_error(one.cameras["c1"].viewpoint.azimuth_deg, seq.truth["cameras"]["c1"]["azimuth_deg"]) < 30


def test_crops_carry_no_motion_cue(small_model, sequences):
    tracks = tracks_from_sequence(sequences[2])
    crops = {name: CameraTrack(t.silhouettes, t.boxes, full_frame=False) for name, t in tracks.items()}
    est = estimate_walk(crops, small_model)
    for cam in est.cameras.values():
        assert cam.cue is None
        assert any("no motion cue" in n for n in cam.notes)


def test_rejects_inconsistent_windows(small_model, sequences):
    tracks = tracks_from_sequence(sequences[0])
    short = CameraTrack(tracks["c1"].silhouettes[:10], tracks["c1"].boxes[:10])
    with pytest.raises(ValueError, match="different numbers of frames"):
        estimate_walk({"c0": tracks["c0"], "c1": short}, small_model)
    with pytest.raises(ValueError, match="no cameras"):
        estimate_walk({}, small_model)


def test_cli_estimate(small_model_path, sequences, tmp_path, capsys):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, sequences[3])
    out = tmp_path / "result.json"
    assert main(["estimate", str(seq_dir), "--out", str(out), "--model", small_model_path]) == 0
    result = json.loads(out.read_text())
    assert result["joint_names"][0] == "head" and len(result["frames"]) == 30
    assert set(result["cameras"]) == {"c0", "c1"}
    assert "truth" in capsys.readouterr().out


def test_cli_a_camera_missing_its_last_frames_has_no_data_there(small_model_path, sequences, tmp_path):
    """A missing PNG is a frame without data, at the end of a camera's frames too (as REST jobs)."""
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, sequences[0])
    for k in range(20, 30):
        os.remove(seq_dir / "c1" / f"{k:06d}.png")
    out = tmp_path / "r.json"
    assert main(["estimate", str(seq_dir), "--out", str(out), "--model", small_model_path,
                 "--posture", "model"]) == 0
    frames = json.loads(out.read_text())["frames"]
    assert len(frames) == 30
    assert all("c1" in f["joints2d"] for f in frames[:20]) and all("c1" not in f["joints2d"] for f in frames[20:])
    assert all("c0" in f["joints2d"] for f in frames)


@pytest.mark.parametrize("breakage", ["empty", "bad_png", "no_rig"])
def test_cli_bad_input_exit_2(small_model_path, sequences, tmp_path, capsys, breakage):
    seq_dir = tmp_path / "seq"
    write_sequence(seq_dir, sequences[0])
    if breakage == "empty":
        shutil.rmtree(seq_dir / "c1")
        os.makedirs(seq_dir / "c1")
        expected = "no PNG silhouettes"
    elif breakage == "bad_png":
        (seq_dir / "c0" / "000003.png").write_bytes(b"\x89PNG broken")
        expected = "not a readable PNG"
    else:
        os.remove(seq_dir / "rig.json")
        expected = "rig.json is missing"
    assert main(["estimate", str(seq_dir), "--out", str(tmp_path / "r.json"), "--model", small_model_path]) == 2
    assert expected in capsys.readouterr().err
    assert not (tmp_path / "r.json").exists()


def test_empty_silhouettes_are_no_walk(small_model, sequences):
    tracks = tracks_from_sequence(sequences[0])
    blank = {
        name: CameraTrack([np.zeros((40, 20), np.uint8)] * 30, np.tile([0.0, 0.0, 20.0, 40.0], (30, 1)))
        for name in tracks
    }
    with pytest.raises(ValueError, match="no non-empty silhouette"):
        estimate_walk(blank, small_model)


def test_camera_without_data_gives_strict_json(small_model, sequences):
    tracks = tracks_from_sequence(sequences[1])
    tracks["c1"] = CameraTrack([None] * 30, np.full((30, 4), np.nan))
    result = estimate_walk(tracks, small_model).to_result()
    json.dumps(result, allow_nan=False)  # no NaN tokens
    assert result["cameras"]["c1"]["azimuth_deg"] is None and result["cameras"]["c0"]["azimuth_deg"] is not None


def test_padded_crops_keep_their_scale(small_model, sequences):
    """A crop with padding around the silhouette: joints2d fit the silhouette, not the PNG."""
    seq = sequences[2]
    tracks = tracks_from_sequence(seq)
    padded = [np.pad(s, 20) for s in tracks["c0"].silhouettes]
    seq.silhouettes = {"c0": padded}
    seq.cameras = ["c0"]
    crops = tracks_from_sequence(seq)
    assert not crops["c0"].full_frame
    est = estimate_walk(crops, small_model)
    j = est.cameras["c0"].joints2d
    heights = np.ptp(j[:, :, 1], axis=1)
    sil_h = np.array([s.shape[0] - 40 for s in padded])
    assert np.all(heights < sil_h)  # the joints lie within the silhouette's height, not the padded PNG's


def test_a_shadow_cut_off_the_feet_leaves_the_motion_cue_to_the_head(small_model):
    """The clean-up's cut (a shadow at the feet) reaches the motion cue: the heights then
    carry the cut's error, so on conflict the head's path decides; the sign stays right."""
    from estimator.damage import damage_sequence
    from estimator.sequence import Sequence

    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=21, azimuths=(30.0, 100.0, 210.0),
                               elevations=(5.0, 15.0, 10.0), image_size=(320, 240)))
    sils = damage_sequence(seq.silhouettes, "shadow", seed=3, truth=seq.truth)
    est = estimate_walk(tracks_from_sequence(Sequence(seq.fps, seq.cameras, seq.image_size, sils, seq.truth)),
                        small_model)
    result = est.to_result()
    for cam in seq.cameras:
        c = est.cameras[cam]
        assert c.cleanup.cut > 0  # the shadow was cut
        # the cut frames are marked on the track (their bottom is the cut: no epipolar tangent there)
        assert est.tracks[cam].cut.sum() == c.cleanup.cut
        assert est.tracks[cam].take(np.arange(5, 12)).cut.tolist() == est.tracks[cam].cut[5:12].tolist()
        assert c.cue.source in ("head", "head+height")
        assert result["cameras"][cam]["motion_cue"]["growth_from"] == c.cue.source
        cos = np.cos(np.radians(seq.truth["cameras"][cam]["azimuth_deg"]))
        if abs(cos) > 0.3:
            assert c.cue.signs()[0] == np.sign(cos)


def contested_shadow_walk(mocap_dir: str):
    """A shadow cut at the feet of a walker who speeds up (CMU 07_05), 3 cameras x 30 frames:
    ``(sequence, tracks)``; two cameras' motion cues point the wrong way."""
    from estimator.damage import damage_sequence
    from estimator.mocap import read_motion
    from estimator.sequence import Sequence

    shape = BodyShape(height=1.88, leg_length=1.09, arm_length=0.90, trunk_length=1.07, shoulder_width=0.95,
                      hip_width=1.02, girth=1.12)
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=23003, shape=shape, image_size=(320, 240)),
                     motion=read_motion(os.path.join(mocap_dir, "07_05.amc")))
    sils = damage_sequence(seq.silhouettes, "shadow", seed=23003, truth=seq.truth)
    return seq, tracks_from_sequence(Sequence(seq.fps, seq.cameras, seq.image_size, sils, seq.truth))


def test_cameras_whose_motion_cue_is_contested_take_the_side_the_other_cameras_phase_agrees_with(
        small_model, mocap_dir):
    """A shadow cut at the feet of a walker who speeds up (CMU 07_05): height and head
    disagree on whether the walker approaches, the head wins and puts two of three
    cameras on the wrong side of the ahead/behind fold (azimuth 180 - a, 75 and 150
    deg off). Those cameras then see the phase half a cycle off the third's; taking
    the sides whose phases agree puts all three within 10 deg."""
    seq, tracks = contested_shadow_walk(mocap_dir)
    true_az = {c: seq.truth["cameras"][c]["azimuth_deg"] for c in seq.cameras}
    alone = estimate_walk(tracks, small_model, config=EstimateConfig(settle_ahead_behind=False))
    wrong = [c for c in seq.cameras if az_error(alone.cameras[c].viewpoint.azimuth_deg, true_az[c]) > 60]
    assert len(wrong) == 2 and all(alone.cameras[c].cue.conflict for c in wrong)  # the failure, without

    est = estimate_walk(tracks, small_model)
    for c in seq.cameras:
        assert az_error(est.cameras[c].viewpoint.azimuth_deg, true_az[c]) < 10, c
    for c in wrong:
        assert est.cameras[c].viewpoint.flip == "cameras"
        assert any("settled by the other cameras" in n for n in est.cameras[c].notes)
    true_phase = np.array([f["phase"] for f in seq.truth["frames"]])
    assert np.median(phase_error(est.phase, true_phase)) < 0.1 < np.median(phase_error(alone.phase, true_phase))
    assert est.to_result()["cameras"][wrong[0]]["motion_cue"]["growth_contested"] is True


def test_one_camera_or_agreeing_cues_are_left_as_the_cues_say(sequences, small_model):
    """Nothing to settle: every camera's cue is uncontested, or only one camera sees."""
    seq = sequences[0]
    tracks = tracks_from_sequence(seq)
    est = estimate_walk(tracks, small_model)
    off = estimate_walk(tracks, small_model, config=EstimateConfig(settle_ahead_behind=False))
    for c in seq.cameras:
        assert est.cameras[c].viewpoint.azimuth_deg == off.cameras[c].viewpoint.azimuth_deg
        assert est.cameras[c].viewpoint.flip != "cameras"
    one = estimate_walk({seq.cameras[0]: tracks[seq.cameras[0]]}, small_model)
    assert one.cameras[seq.cameras[0]].viewpoint.flip != "cameras"


def test_the_shift_search_at_the_decoded_phases_is_exact(small_model, sequences):
    """_cloud_at_phases tries the shifts only where the triangle inequality lets them matter:
    its cloud is the one of the exhaustive search over every shift and example."""
    from estimator.exemplars import hamming, pack
    from estimator.pipeline import _cloud, _cloud_at_phases, _rows_by_phase

    index = small_model.exemplars()
    config = EstimateConfig(phase_shift_px=2)
    track = tracks_from_sequence(sequences[1])[sequences[1].cameras[0]]
    registered, tf = small_model.register([s for s in track.silhouettes if s is not None])
    registered = registered[tf.valid]
    states = np.random.default_rng(0).integers(0, index.n_phases, len(registered))
    by_phase = _rows_by_phase(index)
    r = config.phase_shift_px
    shifts = [(dy, dx) for dy in range(-r, r + 1) for dx in range(-r, r + 1) if dy == 0 or dx == 0]
    rows, dists = [], []
    for reg, k in zip(registered, states):
        moved = pack(np.stack([np.roll(reg, sh, axis=(0, 1)) for sh in shifts]))
        rows.append(by_phase[k])
        dists.append(hamming(moved, index.bits[by_phase[k]]).min(axis=0))
    want = _cloud(index, rows, dists, config)
    got = _cloud_at_phases(index, by_phase, registered, states, config)
    for field in ("az", "el", "w", "frame", "best"):
        np.testing.assert_array_equal(getattr(got, field), getattr(want, field))


def test_a_match_cache_changes_nothing_but_the_work(small_model):
    """Overlapping windows estimated with a MatchCache give the estimates they give without;
    the second window's shared frames are found in it."""
    from estimator.matchcache import MatchCache
    from estimator.windows import window_tracks

    seq = synthesize(SynthSpec(n_cameras=2, n_frames=30, seed=3, image_size=(320, 240)))
    full = tracks_from_sequence(seq)
    cache = MatchCache()
    for k, a in enumerate((0, 10)):
        plain = estimate_walk(window_tracks(full, a, a + 20), small_model)
        hits = cache.hits
        cached = estimate_walk(window_tracks(full, a, a + 20), small_model, cache=cache)
        np.testing.assert_array_equal(cached.states, plain.states)
        for cam in seq.cameras:
            assert cached.cameras[cam].viewpoint.azimuth_deg == plain.cameras[cam].viewpoint.azimuth_deg
            np.testing.assert_array_equal(cached.cameras[cam].labels, plain.cameras[cam].labels)
        assert json.dumps(cached.to_result(), default=str) == json.dumps(plain.to_result(), default=str)
        if k:  # frames 10-19 were matched in the first window
            assert cache.hits - hits >= 2 * 10
    # what depends on a silhouette and a window's choices is kept too: its nearest clusters' members,
    # the examples at its decoded phase, at the grid viewpoints near its camera's
    tags = {t[0] for e in cache._entries.values() for t in e.derived}
    assert tags == {"members", "phase", "cell"}
    small = MatchCache(max_entries=5)
    estimate_walk(window_tracks(full, 0, 20), small_model, cache=small)
    assert len(small) == 5


def test_derived_results_are_computed_once_per_silhouette_and_tag(small_model):
    """MatchCache.derived: compute runs on the silhouettes missing the tag only; a silhouette the
    cache does not hold is computed every time and not kept; tags may differ per silhouette."""
    from estimator.matchcache import MatchCache, derived, match

    cache = MatchCache()
    sils = [np.pad(np.ones((40 + 5 * k, 15), np.uint8), 2) for k in range(3)]
    keys = match(small_model, sils[:2], cache).keys + [MatchCache.key(sils[2])]  # the third is not held
    calls = []

    def compute(todo):
        calls.append(todo.tolist())
        return [10 * int(i) for i in todo]

    assert cache.derived(keys, "a", compute) == [0, 10, 20]
    assert cache.derived(keys, "a", compute) == [0, 10, 20]
    assert calls == [[0, 1, 2], [2]]  # the unheld third silhouette again, the held two not
    assert cache.derived(keys, ["a", "b", "a"], compute) == [0, 10, 20] and calls[-1] == [1, 2]
    assert derived(None, None, 2, "a", compute) == [0, 10] and calls[-1] == [0, 1]  # no cache: all


def test_a_camera_out_of_step_with_the_others_has_a_large_phase_offset(small_model):
    """Three cameras of one walk, the third's frames half a gait cycle later (7 frames at 0.072 cycles per
    frame): the phase decoded from all three follows the two that agree, and the third's observations
    sit about half a cycle from it (``phase_offset``, in the result as each camera's ``phase_offset``)."""
    from estimator.pipeline import phase_offset

    seq = synthesize(SynthSpec(n_cameras=3, n_frames=40, seed=4, elevations=(0.0, 15.0, 5.0), image_size=(320, 240)))
    tracks = tracks_from_sequence(seq)
    cut = {c: CameraTrack(t.silhouettes[k:k + 24], t.boxes[k:k + 24], t.full_frame, t.image_size)
           for (c, t), k in zip(tracks.items(), (0, 0, 7))}
    result = estimate_walk(cut, small_model).to_result()
    offsets = {c: result["cameras"][c]["phase_offset"] for c in cut}
    assert offsets["c0"] < 0.1 and offsets["c1"] < 0.1 and offsets["c2"] > 0.3, offsets
    doubtful = {c: any("out of step" in n for n in result["cameras"][c]["notes"]) for c in cut}
    assert doubtful == {"c0": False, "c1": False, "c2": True}
    alone = estimate_walk({"c2": cut["c2"]}, small_model).to_result()["cameras"]["c2"]  # alone it is the phase
    assert alone["phase_offset"] < 0.1 and not any("out of step" in n for n in alone["notes"])
    assert phase_offset(np.array([0.1, np.nan, 0.95]), np.zeros(3)) is None  # fewer than 3 observations
    assert phase_offset(np.array([0.1, 0.6, 0.95, 0.5]), np.array([0.0, 0.5, 0.0, 0.5])) == 0.075


def test_a_camera_on_too_few_frames_is_set_aside_while_another_has_enough(small_model):
    """A camera whose walker shows on 5 frames of a 30-frame window, beside one that shows on all: no
    viewpoint, phase nor joints from it, a note saying why, and the other camera estimated as if alone.
    Alone, or with ``min_frames`` 0, the same 5 frames are estimated (the window has nothing better)."""
    tracks = tracks_from_sequence(synthesize(SynthSpec(n_cameras=2, n_frames=30, seed=2, elevations=(0.0, 15.0),
                                                       image_size=(320, 240))))
    t0 = tracks["c0"]
    thin = CameraTrack([s if k < 5 else None for k, s in enumerate(t0.silhouettes)],
                       np.where(np.arange(30)[:, None] < 5, t0.boxes, np.nan), t0.full_frame, t0.image_size)
    result = estimate_walk({"c0": thin, "c1": tracks["c1"]}, small_model).to_result()
    c0 = result["cameras"]["c0"]
    assert c0["azimuth_deg"] is None and c0["phase_offset"] is None
    assert any("matched on 5 frames" in n and "fewer than 6" in n for n in c0["notes"]), c0["notes"]
    assert not any("c0" in f["joints2d"] or "c0" in f["seen_by"] for f in result["frames"])
    assert all(f["observed_phase"]["c0"] is None for f in result["frames"])
    alone = estimate_walk({"c1": tracks["c1"]}, small_model).to_result()
    assert abs(result["cameras"]["c1"]["azimuth_deg"] - alone["cameras"]["c1"]["azimuth_deg"]) < 0.5
    assert [f["phase"] for f in result["frames"]] == [f["phase"] for f in alone["frames"]]
    kept = estimate_walk({"c0": thin, "c1": tracks["c1"]}, small_model, config=EstimateConfig(min_frames=0))
    assert np.isfinite(kept.cameras["c0"].viewpoint.azimuth_deg)
    assert np.isfinite(estimate_walk({"c0": thin}, small_model).cameras["c0"].viewpoint.azimuth_deg)


def test_a_camera_seen_on_few_frames_takes_the_side_the_other_cameras_phase_agrees_with(small_model):
    """The first camera's frames half a gait cycle later than the others' (7 frames), so its motion cue
    says one side of the ahead/behind fold and the other cameras' phase the other. On 6 frames the
    phase decides (``settle_few_frames``, 10: a size change over a few frames is the weaker evidence),
    and a note says why; on 24 frames, with the rule off, or where no camera is seen on 10 frames
    (their phase no surer than the cue: a walk of 8 frames), the cue does."""
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=40, seed=4, azimuths=(30.0, 110.0, 250.0),
                               elevations=(5.0, 10.0, 15.0), image_size=(320, 240)))
    tracks = tracks_from_sequence(seq)
    cut = {c: CameraTrack(t.silhouettes[k:k + 24], t.boxes[k:k + 24], t.full_frame, t.image_size)
           for (c, t), k in zip(tracks.items(), (7, 0, 0))}
    kept = np.arange(24) < 6
    t0 = cut["c0"]
    few = {**cut, "c0": CameraTrack([s if k else None for k, s in zip(kept, t0.silhouettes)],
                                    np.where(kept[:, None], t0.boxes, np.nan), t0.full_frame, t0.image_size)}

    def c0(tracks, **config):
        return estimate_walk(tracks, small_model, config=EstimateConfig(**config)).cameras["c0"]

    settled = c0(few)
    assert settled.viewpoint.flip == "cameras" and az_error(settled.viewpoint.azimuth_deg, 150.0) < 25
    assert any("measured on 6 frames only" in n for n in settled.notes), settled.notes
    for cue in (c0(few, settle_few_frames=0), c0(cut)):
        assert cue.viewpoint.flip == "motion" and az_error(cue.viewpoint.azimuth_deg, 30.0) < 25
    # Every camera on 8 frames: the others' phase is no surer than the cue (this walk's c1 was put behind).
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=8, seed=7, azimuths=(90.0, 30.0), elevations=(5.0, 10.0),
                               shape=BodyShape(girth=0.85)))
    c1 = estimate_walk(tracks_from_sequence(seq), small_model).cameras["c1"]
    assert c1.viewpoint.flip == "motion" and az_error(c1.viewpoint.azimuth_deg, 30.0) < 25, c1.viewpoint


def out_of_step_walk(shift: int) -> dict[str, CameraTrack]:
    """Three cameras (30, 110 and 250 deg) on 24 frames, the first one's ``shift`` frames later than
    the others' (7: half a gait cycle, so its phase says the mirror of what its motion cue says)."""
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=40, seed=4, azimuths=(30.0, 110.0, 250.0),
                               elevations=(5.0, 10.0, 15.0), image_size=(320, 240)))
    return {c: CameraTrack(t.silhouettes[k:k + 24], t.boxes[k:k + 24], t.full_frame, t.image_size)
            for (c, t), k in zip(tracks_from_sequence(seq).items(), (shift, 0, 0))}


def test_a_camera_keeps_the_side_its_earlier_windows_found_unless_the_others_phase_objects(small_model):
    """A fixed camera's earlier windows are evidence of its ahead/behind (``earlier``, the live service's
    smoothed viewpoints). The first camera's frames half a gait cycle later than the others', on 24
    frames: its motion cue says 30 deg, the others' phase its mirror, 150. Earlier windows at 150 take
    it there, with a note; at 30, or with the walker turned (no camera where its earlier windows put
    it), the cue stands; in step with the others, earlier windows at 150 are not followed (their phase
    objects)."""
    def c0(shift: int, earlier: dict[str, float] | None):
        return estimate_walk(out_of_step_walk(shift), small_model, earlier=earlier).cameras["c0"]

    rest = {"c1": 110.0, "c2": 250.0}
    held = c0(7, {"c0": 150.0, **rest})
    assert held.viewpoint.flip == "earlier" and az_error(held.viewpoint.azimuth_deg, 150.0) < 25, held.viewpoint
    assert any("earlier windows found (150 deg)" in n for n in held.notes), held.notes
    turned = {"c0": 150.0, "c1": 290.0, "c2": 70.0}
    for earlier in (None, {"c0": 30.0, **rest}, turned):
        cue = c0(7, earlier)
        assert cue.viewpoint.flip == "motion" and az_error(cue.viewpoint.azimuth_deg, 30.0) < 25, (earlier,
                                                                                                  cue.viewpoint)
    in_step = c0(0, {"c0": 150.0, **rest})
    assert az_error(in_step.viewpoint.azimuth_deg, 30.0) < 25, in_step.viewpoint
    # No motion cue (crops): the others' phase takes it to 150 by itself; the earlier windows agreeing is no hold.
    tracks = out_of_step_walk(7)
    tracks["c0"] = dataclasses.replace(tracks["c0"], full_frame=False)
    for earlier in (None, {"c0": 150.0, **rest}):
        cropped = estimate_walk(tracks, small_model, earlier=earlier).cameras["c0"]
        assert cropped.viewpoint.flip == "cameras" and az_error(cropped.viewpoint.azimuth_deg, 150.0) < 25, (
            earlier, cropped.viewpoint)
