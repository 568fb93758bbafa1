"""A recording as sliding windows, one segment per heading of the walker (estimator.windows)."""

import json

import numpy as np
import pytest

from conftest import TURN_AFTER as AFTER, TURN_BEFORE as BEFORE
from estimator.pipeline import estimate_walk, tracks_from_sequence
from estimator.sequence import write_sequence
from estimator.synth import SynthSpec, synthesize
from estimator.windows import segment_walk, window_starts
from service.cli import main


def az_error(a, b):
    return abs((a - b + 180.0) % 360.0 - 180.0)


def phase_hits(phase, truth):
    return np.mean(np.abs((np.asarray(phase, float) - np.asarray(truth) + 0.5) % 1.0 - 0.5) <= 0.1)


def _walk(azimuths, seed, n=40):
    return synthesize(SynthSpec(n_cameras=2, n_frames=n, seed=seed, azimuths=azimuths, elevations=(10.0, 10.0),
                                image_size=(320, 240)))


@pytest.fixture(scope="module")
def turn(turn_sequence):
    return turn_sequence


@pytest.fixture(scope="module")
def straight():
    return _walk(BEFORE, 3, n=60)


def test_window_starts():
    assert window_starts(15, 20, 10).tolist() == [0]  # short: one window of everything
    assert window_starts(20, 20, 10).tolist() == [0]
    assert window_starts(40, 20, 10).tolist() == [0, 10, 20]
    assert window_starts(45, 20, 10).tolist() == [0, 10, 20, 25]  # the last one ends at the end
    with pytest.raises(ValueError, match="positive"):
        window_starts(40, 20, 0)


def test_a_straight_walk_is_one_segment_as_one_window(small_model, straight):
    tracks = tracks_from_sequence(straight)
    walk = segment_walk(tracks, small_model)
    whole = estimate_walk(tracks, small_model)
    assert len(walk.segments) == 1 and len(walk.windows) == 5
    result = walk.to_result()
    assert [f["index"] for f in result["frames"]] == list(range(60))
    np.testing.assert_array_equal([f["phase"] for f in result["frames"]], np.round(whole.phase, 4))
    for cam in straight.cameras:
        assert result["cameras"][cam]["azimuth_deg"] == round(whole.cameras[cam].viewpoint.azimuth_deg, 3)
    assert all(w["segment"] == 0 for w in result["windows"])


def test_a_turn_splits_the_recording_where_the_viewpoints_change(small_model, turn):
    tracks = tracks_from_sequence(turn)
    result = segment_walk(tracks, small_model).to_result()
    json.dumps(result, allow_nan=False)
    segs = result["segments"]
    assert len(segs) == 2, [(s["first_index"], s["last_index"]) for s in segs]
    assert segs[0]["first_index"] == 0 and segs[1]["last_index"] == 79
    assert segs[1]["first_index"] == segs[0]["last_index"] + 1 and 30 <= segs[1]["first_index"] <= 50
    for seg, truth in zip(segs, (BEFORE, AFTER)):
        for cam, az in zip(("c0", "c1"), truth):
            assert az_error(seg["cameras"][cam]["azimuth_deg"], az) < 25, (seg, cam)
    assert [f["index"] for f in result["frames"]] == list(range(80))
    assert all(f["segment"] == (0 if f["index"] <= segs[0]["last_index"] else 1) for f in result["frames"])
    assert any("2 segments" in n for n in result["notes"])
    # One window over the whole recording mixes both headings: no single heading explains
    # its cameras' viewpoints (the robust viewpoint weighting lets each camera take the
    # half it sees best, so its phase no longer suffers: measured 0.94 for both).
    truth_phase = [f["phase"] for f in turn.truth["frames"]]
    whole = estimate_walk(tracks, small_model)
    assert not any(all(az_error(whole.cameras[c].viewpoint.azimuth_deg, az) < 25 for c, az in zip(("c0", "c1"), half))
                   for half in (BEFORE, AFTER))
    segmented = phase_hits([f["phase"] for f in result["frames"]], truth_phase)
    assert segmented > 0.85 and segmented >= phase_hits(whole.phase, truth_phase) - 0.05


def test_frames_without_the_walker_are_reported_empty_not_dropped(small_model, turn):
    tracks = tracks_from_sequence(turn)
    for t in tracks.values():
        for k in range(25):
            t.silhouettes[k] = None
            t.boxes[k] = np.nan
    walk = segment_walk(tracks, small_model, length=20, hop=10)
    result = walk.to_result()
    json.dumps(result, allow_nan=False)
    assert len(result["frames"]) == 80
    assert "error" in result["windows"][0] and "no silhouettes" in result["windows"][0]["error"]
    assert result["frames"][5]["joints2d"] == {}  # nobody seen: nothing placed in any image
    assert all(f["joints3d"] is not None for f in result["frames"][40:])
    for t in tracks.values():
        t.silhouettes[:] = [None] * 80
    with pytest.raises(ValueError, match="no silhouettes"):
        segment_walk(tracks, small_model)


def test_priors_come_from_each_frames_segment(small_model, turn):
    from estimator.prior import priors_for_window
    from estimator.render import Renderer
    from estimator.skeleton import BodyShape

    tracks = tracks_from_sequence(turn)
    walk = segment_walk(tracks, small_model)
    whole = estimate_walk(tracks, small_model)
    with Renderer(BodyShape()) as renderer:
        priors = priors_for_window(walk, tracks, turn.image_size, renderer=renderer)
        mixed = priors_for_window(whole, tracks, turn.image_size, renderer=renderer)
    for cam in turn.cameras:
        assert [p.frame_index for p in priors[cam]] == list(range(80))  # each frame once, in order

    def iou(ps, cam, frames):
        out = []
        for k in frames:
            sil, mask = turn.silhouettes[cam][k] > 0, ps[cam][k].full_mask() > 127
            out.append((mask & sil).sum() / (mask | sil).sum())
        return np.mean(out)

    # After the turn, priors rendered at the second segment's viewpoint fit the walker
    # better than priors from one viewpoint for the whole recording.
    after = range(walk.segments[1].first, 80)
    # Measured: 0.83 against 0.17 (c1), 0.93 against 0.67 (c0).
    assert iou(priors, "c1", after) > 0.7 and iou(priors, "c1", after) > iou(mixed, "c1", after) + 0.3


def test_cli_estimate_reports_segments(small_model_path, turn, tmp_path, capsys):
    write_sequence(tmp_path / "seq", turn)
    out = tmp_path / "result.json"
    light = ["--model", small_model_path, "--posture", "model"]  # the segments are under test, not the posture
    assert main(["estimate", str(tmp_path / "seq"), "--out", str(out), *light]) == 0
    result = json.loads(out.read_text())
    assert len(result["segments"]) == 2 and len(result["frames"]) == 80
    assert "2 segments" in capsys.readouterr().out
    assert main(["estimate", str(tmp_path / "seq"), "--out", str(out), *light, "--window", "80"]) == 0
    assert len(json.loads(out.read_text())["segments"]) == 1
    with pytest.raises(SystemExit) as exc:
        main(["estimate", str(tmp_path / "seq"), "--out", str(out), "--hop", "0"])
    assert exc.value.code == 2
