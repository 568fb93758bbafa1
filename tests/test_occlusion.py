"""A walker hidden below (estimator.occlusion): a low wall in front, or the image's bottom edge."""

import json

import numpy as np
import pytest

from estimator.appearance import save_model
from estimator.cleanup import CleanupConfig, astride_edge, edge_share, evenly_spaced, fixed_edge
from estimator.joints import JOINT_INDEX
from estimator.mnbp import posture_sequences
from estimator.mnbp3d import posture_sequence3d
from estimator.damage import _wall_row, damage_sequence
from estimator.mnbp import measure_postures
from estimator.pipeline import (EstimateConfig, estimate_walk, registered_walker_score, tracks_from_sequence,
                                walker_score)
from estimator.rig import calibrate_rig, hidden_joints
from estimator.occlusion import hidden_fraction, hidden_shares
from estimator.registration import register
from estimator.sequence import Sequence
from estimator.synth import SynthSpec, synthesize
from estimator.viewpoint import azimuth_difference_deg, head_points, motion_cue

FRACTIONS = (0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4, 0.45, 0.5)


@pytest.fixture(scope="module")
def walk():
    return synthesize(SynthSpec(n_cameras=2, n_frames=24, seed=5, azimuths=(60.0, 150.0), elevations=(10.0, 10.0),
                                image_size=(320, 240)))


def _true_hidden(clean, cut):
    """The share of each frame's walker height missing from ``cut``, median over the frames."""
    h0, h1 = clean.boxes[:, 3], cut.boxes[:, 3]
    ok = np.isfinite(h0) & np.isfinite(h1)
    return float(np.median(1.0 - h1[ok] / h0[ok]))


def _azimuth_gap(a, b):
    return max(abs(float(azimuth_difference_deg(a.cameras[c].viewpoint.azimuth_deg, b.cameras[c].viewpoint.azimuth_deg)))
               for c in a.cameras)


def test_a_cut_example_registers_onto_the_cut_examples(small_model):
    """An example with its lowest 30 % erased, registered for a walker hidden below, lands on its own
    exemplar as the cut model keeps it; registered as a whole body it does not."""
    h, w = small_model.size
    bits = np.unpackbits(small_model.member_bits[::97], axis=1, count=h * w).reshape(-1, h, w)
    big = np.stack([np.kron(b, np.ones((6, 6), np.uint8)) for b in bits]) * 255  # as a camera sees them
    rows = np.flatnonzero(big.any(axis=(0, 2)))
    for b in big:
        r = np.flatnonzero(b.any(axis=1))
        b[int(round(r[0] + 0.7 * (r[-1] - r[0] + 1))):] = 0
    cut = small_model.hidden_below(0.3)
    kept = np.unpackbits(cut.member_bits[::97], axis=1, count=h * w).reshape(-1, h, w).astype(bool)
    as_cut = (cut.register(list(big))[0].astype(bool) ^ kept).sum(axis=(1, 2))
    as_whole = (small_model.register(list(big))[0].astype(bool) ^ kept).sum(axis=(1, 2))
    assert rows.size and np.median(as_cut) < 0.25 * np.median(as_whole)
    assert np.median(as_cut) < 0.2 * kept.sum(axis=(1, 2)).mean()  # a few edge pixels, from resampling
    assert not cut.means[:, cut.hidden.rows:].any() and not kept[:, cut.hidden.rows:].any()
    assert small_model.hidden_below(0.3) is cut  # built once


def test_hidden_registration_and_the_cut_model_are_checked(small_model, tmp_path):
    with pytest.raises(ValueError, match="hidden"):
        register([np.ones((10, 4), np.uint8)], hidden=0.3)  # no top
    with pytest.raises(ValueError, match="fraction"):
        small_model.hidden_below(1.0)
    with pytest.raises(ValueError, match="already cut"):
        small_model.hidden_below(0.3).hidden_below(0.2)
    with pytest.raises(ValueError, match="derived"):
        save_model(small_model.hidden_below(0.3), tmp_path / "cut.npz")


def test_the_hidden_share_is_found_and_the_viewpoint_kept(walk, small_model):
    """Behind a low wall (15-40 % of the height hidden): the clean-up says so, the share is found within
    0.1, and the viewpoints stay within 10 deg of the clean estimate; matched as a whole body they do not."""
    clean = tracks_from_sequence(walk)
    walled = tracks_from_sequence(Sequence(walk.fps, walk.cameras, walk.image_size,
                                           damage_sequence(walk.silhouettes, "low_wall", seed=0), walk.truth))
    est = estimate_walk(walled, small_model)
    for cam in walk.cameras:
        report = est.cameras[cam].cleanup
        assert report.hidden_by == "something in front" and "hidden by something in front" in report.note()
        assert abs(report.hidden - _true_hidden(clean[cam], walled[cam])) <= 0.1, cam
    ref = estimate_walk(clean, small_model)
    assert _azimuth_gap(est, ref) <= 10
    no_gate = EstimateConfig(cleanup=CleanupConfig(hidden_flat=1.01))  # never said: matched as whole bodies
    assert _azimuth_gap(estimate_walk(walled, small_model, config=no_gate), ref) > 10


def test_a_walker_on_the_bottom_edge_is_matched_by_what_the_frame_shows(walk, small_model):
    """Each camera's frame ends at the walker's knees: every frame is cut by the border, so none is
    skipped; the bottom edge is said to hide the walker and the estimate stays near the whole one."""
    clean = tracks_from_sequence(walk)
    sils, edge = {}, {}
    for cam, frames in walk.silhouettes.items():
        rows = np.concatenate([np.flatnonzero(s.any(axis=1)) for s in frames if s is not None])
        edge[cam] = int(np.median(rows) + 0.2 * np.ptp(rows))  # about 70 % of the body shows
        sils[cam] = [None if s is None else s[:edge[cam]] for s in frames]
    height = min(edge.values())
    sils = {cam: [None if s is None else s[:height] for s in frames] for cam, frames in sils.items()}
    seq = Sequence(walk.fps, walk.cameras, (walk.image_size[0], height), sils, walk.truth)
    est = estimate_walk(tracks_from_sequence(seq), small_model)
    cut = tracks_from_sequence(seq)
    for cam in walk.cameras:
        report = est.cameras[cam].cleanup
        assert report.hidden_by == "the image's bottom edge" and "cut by the image border" not in report.skipped, cam
        assert abs(report.hidden - _true_hidden(clean[cam], cut[cam])) <= 0.1, cam
        placed = est.cameras[cam].joints2d[:, :, 1]
        assert np.nanmax(placed) > height  # the feet are placed below the frame, where they are
    assert _azimuth_gap(est, estimate_walk(clean, small_model)) <= 10


def test_hidden_fraction_is_checked(small_model):
    with pytest.raises(ValueError, match="silhouettes and fractions"):
        hidden_fraction(small_model, [None], FRACTIONS, registered_walker_score)


def test_the_share_search_scores_each_share_as_its_cut_model_does(walk, small_model):
    """The search registers each silhouette at every share at once and scores them in one call: its
    mean score per share is the one :func:`walker_score` gives with the model cut at that share,
    to the bit, on whole walkers and behind a low wall (where a share above 0 fits best)."""
    walled = damage_sequence(walk.silhouettes, "low_wall", seed=0)
    for frames in (walk.silhouettes["c0"], walled["c0"], walled["c1"]):
        best, costs = hidden_fraction(small_model, [None, *frames], (0.0, *FRACTIONS), registered_walker_score,
                                      frames=6)
        sampled = [frames[i] for i in evenly_spaced(len(frames), 6)]
        ref = [np.mean(walker_score(small_model.hidden_below(f, compared=0.4), sampled)) for f in (0.0, *FRACTIONS)]
        assert np.array_equal(costs, ref), (costs, ref)
        assert best == (0.0, *FRACTIONS)[int(np.argmin(ref))]
    assert hidden_fraction(small_model, walled["c0"], (0.0, *FRACTIONS), registered_walker_score)[0] > 0


def test_mnbp_leaves_the_legs_behind_a_wall_where_the_body_puts_them():
    """A walker cut at 70 % of the height: told the rows hidden below, mNBP keeps the shins and feet
    near the truth under the crop; told nothing, it pulls them up onto the visible silhouette."""
    seq = synthesize(SynthSpec(n_cameras=2, n_frames=6, seed=4, azimuths=(90.0, 45.0), elevations=(5.0, 10.0)))
    tracks = tracks_from_sequence(seq)
    low = [JOINT_INDEX[j] for j in ("left_ankle", "right_ankle", "left_knee", "right_knee")]
    told, untold = [], []
    for cam in seq.cameras:
        t = tracks[cam]
        truth = np.array([f["joints2d"][cam] for f in seq.truth["frames"]])
        sils, boxes = [], t.boxes.copy()
        for s, b in zip(t.silhouettes, boxes):
            keep = int(round(0.7 * s.shape[0]))
            sils.append(s[:keep])
            b[3] = keep
        hidden = np.full(len(sils), 0.3)
        for h, out in ((hidden, told), (None, untold)):
            joints, _ = (j[0] for j in posture_sequences([sils], [boxes], [truth], hidden=None if h is None else [h]))
            out.append(np.linalg.norm(joints[:, low] - truth[:, low], axis=-1) / t.boxes[:, 3:4])
    told, untold = np.concatenate(told), np.concatenate(untold)
    # measured: 0.019 and 0.111 of the height
    assert np.median(told) < 0.05 and np.median(told) < 0.5 * np.median(untold), (np.median(told), np.median(untold))



def test_the_3d_round_leaves_the_legs_behind_a_wall_where_the_views_put_them():
    """The 3D round (estimator.mnbp3d) told of the rows hidden below every view: knees and ankles
    stay near the truth; told nothing, every view pulls them up onto its silhouette's bottom."""
    from test_mnbp3d import _walk

    seq, cams, world, sils, boxes = _walk(4)
    stature = seq.truth["body"]["height"]
    cut = [[s[:int(round(0.7 * s.shape[0]))] for s in cam] for cam in sils]
    boxes = boxes.copy()
    boxes[..., 3] = np.array([[s.shape[0] for s in cam] for cam in cut])
    hidden = [np.full(len(cam), 0.3) for cam in cut]
    low = [JOINT_INDEX[j] for j in ("left_ankle", "right_ankle", "left_knee", "right_knee")]
    err = {}
    for told in (True, False):
        out, _ = posture_sequence3d(cut, boxes, cams, world, stature=stature, hidden=hidden if told else None)
        err[told] = np.median(np.linalg.norm(out[:, low] - world[:, low], axis=-1)) / stature
    assert err[True] < 0.04 and err[True] < 0.6 * err[False], err  # measured: 0.022 and 0.154 of the stature


def test_behind_a_wall_the_elevation_comes_from_the_path_and_hidden_joints_weigh_less(small_model):
    """The shape tells the elevation mostly by the legs: behind a wall the head's image path gives it
    (each camera nearer the truth than by the shape alone: 7.7 and 2.1 deg off against 13.5 and 7.8
    with the small model); mNBP's joints under the
    visible part are marked hidden, and the rig weighs them less."""
    walk = synthesize(SynthSpec(n_cameras=2, n_frames=24, seed=5, azimuths=(60.0, 150.0), elevations=(30.0, 20.0),
                                image_size=(320, 240)))
    walled = tracks_from_sequence(Sequence(walk.fps, walk.cameras, walk.image_size,
                                           damage_sequence(walk.silhouettes, "low_wall", seed=0), walk.truth))
    truth = [walk.truth["cameras"][c]["elevation_deg"] for c in walk.cameras]
    est = estimate_walk(walled, small_model)
    shape = estimate_walk(walled, small_model, config=EstimateConfig(path_elevation=False))
    off = [abs(e.cameras[c].viewpoint.elevation_deg - t) for e in (est, shape) for c, t in zip(walk.cameras, truth)]
    assert max(off[:2]) <= 8.0 and off[0] < off[2] and off[1] < off[3], off  # the small model's 3 elevations
    assert all(c.viewpoint.elevation_from == "shape+path" for c in est.cameras.values())
    measured = measure_postures(est)
    below = hidden_joints(measured, tuple(measured.cameras))
    for k, cam in enumerate(walk.cameras):
        bottom = (est.tracks[cam].boxes[:, 1] + est.tracks[cam].boxes[:, 3])[:, None]
        joints = measured.cameras[cam].joints2d
        assert np.array_equal(below[k], joints[..., 1] > bottom)
        assert below[k][:, JOINT_INDEX["left_ankle"]].all() and not below[k][:, JOINT_INDEX["head"]].any()
    assert not hidden_joints(measure_postures(estimate_walk(tracks_from_sequence(walk), small_model)),
                             tuple(walk.cameras)).any()  # nothing hidden, nothing marked
    rig = calibrate_rig(measured)
    assert rig.source == "self-calibration"
    assert any(f"joints placed below a silhouette hidden below weighed {0.3}" in n for n in rig.notes), rig.notes


def _heights(frames):
    return np.array([np.nan if s is None or not s.any() else np.ptp(np.flatnonzero(s.any(axis=1))) + 1.0
                     for s in frames])


def test_each_frame_behind_a_fixed_wall_hides_its_own_share():
    """A wall's edge is fixed in the image: as the walker nears a camera that looks over it, more of
    them is hidden and the visible height shrinks. The whole height follows the head's growth, so
    the share per frame comes back exactly from the growth and the window's median share."""
    t = np.arange(30.0)
    whole = 120.0 * np.exp(0.012 * t)  # nearing: 120 -> 170 px
    visible = 100.0 - 0.2 * (whole - 120.0)  # the head comes down towards the edge: 100 -> 90 px
    truth = 1.0 - visible / whole
    got = hidden_shares(visible, 0.012, float(np.median(truth)))
    assert np.allclose(got, truth, atol=1e-9) and truth[-1] - truth[0] > 0.25
    # The walker passed the wall's end on the first 10 frames: their heights are the whole ones.
    passed = t < 10
    shown = np.where(passed, whole, visible)
    got = hidden_shares(shown, 0.012, 0.9, whole=passed)  # the share is not needed then
    assert np.allclose(got, np.where(passed, 0.0, truth), atol=1e-9)
    with_gap = visible.copy()
    with_gap[[3, 7]] = np.nan
    assert np.isnan(hidden_shares(with_gap, 0.012, 0.3)[[3, 7]]).all()
    assert np.all(hidden_shares(visible, 0.05, 0.3, most=0.8) <= 0.8)  # clipped


def test_a_fixed_wall_is_told_by_its_row_and_the_walker_size_by_the_head(small_model):
    """Behind a wall fixed in the image (``fixed_wall``), cameras 5 m away look down 25 deg on a
    walker who nears one and leaves the other: the clean-up says the silhouettes end on a fixed edge
    even when the silhouettes' fit to the examples would not tell it (``hidden_gain`` out of reach),
    each frame gets its own share (0.03 of the height from the truth in the median, 0.08 at most;
    one share per window is more than 0.15 off at the ends), the growth is the head's (its width and
    path), with the right sign, and the azimuths stay within 10 deg.
    A whole walker and one behind a wall that moves with them (``low_wall``) end on no fixed edge."""
    walk = synthesize(SynthSpec(n_cameras=2, n_frames=24, seed=5, azimuths=(20.0, 160.0), elevations=(25.0, 25.0),
                                image_size=(320, 240), distance=5.0))
    sils = damage_sequence(walk.silhouettes, "fixed_wall", seed=0, truth=walk.truth)
    walled = tracks_from_sequence(Sequence(walk.fps, walk.cameras, walk.image_size, sils, walk.truth))
    est = estimate_walk(walled, small_model, config=EstimateConfig(cleanup=CleanupConfig(hidden_gain=1.01)))
    for cam, sign in zip(walk.cameras, (1, -1)):
        c = est.cameras[cam]
        truth = 1.0 - _heights(sils[cam]) / _heights(walk.silhouettes[cam])
        assert np.ptp(truth) > 0.3
        edge = c.cleanup.on_edge
        assert c.cleanup.hidden_by == "something in front" and edge.sum() >= 20
        assert np.sum(edge != (truth > 0.02)) <= 1, (edge, truth)  # the frames behind it, not those above it
        assert f"{edge.sum()} of 24 frames end on one image row" in c.cleanup.note()
        err = np.abs(est.tracks[cam].hidden - truth)
        assert np.median(err) <= 0.03 and err.max() <= 0.08, (cam, err)  # the whole height bobs with the gait
        assert np.abs(np.median(truth) - truth).max() > 0.15
        assert c.cue.source in ("head width", "head+head width"), c.cue.source
        assert np.sign(c.cue.growth) == sign and abs(c.cue.growth) > 3 * c.cue.growth_se
        assert abs(azimuth_difference_deg(c.viewpoint.azimuth_deg, walk.truth["cameras"][cam]["azimuth_deg"])) <= 10
        # The visible height says the opposite of the growth.
        assert np.sign(np.polyfit(np.arange(24), np.log(_heights(sils[cam])), 1)[0]) == -sign
    for kind in ("clean", "low_wall"):
        frames = walk.silhouettes if kind == "clean" else damage_sequence(walk.silhouettes, kind, seed=0)
        tracks = tracks_from_sequence(Sequence(walk.fps, walk.cameras, walk.image_size, frames, walk.truth))
        assert not any(fixed_edge(t.silhouettes, t.boxes).any() for t in tracks.values()), kind


def test_the_motion_cue_without_heights_is_the_heads():
    """``heights=False``: the growth is the head path's alone, and no evidence without one."""
    walk = synthesize(SynthSpec(n_cameras=1, n_frames=24, seed=5, azimuths=(20.0,), elevations=(10.0,),
                                image_size=(320, 240), distance=5.0))
    t = tracks_from_sequence(walk)["c0"]
    heads = head_points(t.silhouettes, t.boxes)
    both, head = motion_cue(t.boxes, heads), motion_cue(t.boxes, heads, heights=False)
    assert head.source == "head" and both.source != "head" and head.growth > 3 * head.growth_se > 0
    none = motion_cue(t.boxes, heights=False)
    assert none.source == "none" and none.growth == 0.0 and none.growth_se == np.inf and none.signs()[0] == 0


def _walker_behind_a_wall(accel: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Boxes, head points and head widths of a walker's visible part (the head 6 m from a 500 px
    pinhole camera, walking at 1.3 m/s towards it and across at 45 deg, ``accel`` m/s^2), over 2 s at
    15 Hz; and the true growth of their image per frame."""
    t = np.arange(30) / 15.0
    head = np.array([-1.5, -0.2, 6.0]) + (1.3 * t + accel * t**2 / 2)[:, None] * np.array([0.7071, 0.0, -0.7071])
    u, v, width = 320 + 500 * head[:, 0] / head[:, 2], 240 + 500 * head[:, 1] / head[:, 2], 500 * 0.15 / head[:, 2]
    boxes = np.stack([u - width, v, 2 * width, 500 * 1.0 / head[:, 2]], axis=1)  # the wall hides the rest
    growth = np.polyfit(np.arange(30), -np.log(head[:, 2]), 1)[0]
    return boxes, np.stack([u, v], axis=1), np.round(4 * width) / 4, float(growth)  # a band's mean width


def test_behind_a_wall_the_heads_width_tells_a_walker_who_slows_down():
    """No height tells the walker's size (a wall across the window). A walker who nears the camera
    while slowing down bends the head's image path as a receding one would (CMU 07_05 does); the
    head's width grows as they near it whatever their speed, and counts alone where the two
    disagree (``conflict`` says so). At a steady speed the two are combined."""
    boxes, heads, widths, truth = _walker_behind_a_wall(accel=-0.7)
    path = motion_cue(boxes, heads, heights=False)
    assert truth > 0 and path.growth < -3 * path.growth_se  # the path alone: the wrong way
    cue = motion_cue(boxes, heads, heights=False, head_widths=widths)
    assert cue.source == "head width" and cue.conflict and cue.signs()[0] == 1
    assert abs(cue.growth - truth) < 0.1 * truth, (cue.growth, truth)
    boxes, heads, widths, truth = _walker_behind_a_wall(accel=0.0)
    steady = motion_cue(boxes, heads, heights=False, head_widths=widths)
    assert steady.source == "head+head width" and not steady.conflict
    assert abs(steady.growth - truth) < 0.1 * truth, (steady.growth, truth)
    with pytest.raises(ValueError, match="head_widths"):
        motion_cue(boxes, heads, heights=False, head_widths=widths[:-1])
    assert motion_cue(boxes, heads, head_widths=widths).source == "head+height"  # heights first, where they tell


def test_a_small_side_view_walkers_flat_feet_are_not_a_wall():
    """A walker 53-55 px tall seen from the side, at one depth over the window, rests a flat foot on
    one image row in every frame, as a wall's top does, and no frame off that row tells the two apart
    (docs/ROBUSTNESS.md, "Flat feet on one row"): with a tenth of their height under ``fixed_rows``
    rows, no edge is taken. A real wall over 20 of 24 frames of a larger walker is still told (the test
    above, ``fixed_wall``)."""
    spec = SynthSpec(n_cameras=2, n_frames=20, seed=1, azimuths=(90.0, 270.0), elevations=(20.0, 15.0),
                     image_size=(128, 96))
    tracks = tracks_from_sequence(synthesize(spec))
    heights = [np.nanmedian(t.boxes[:, 3]) for t in tracks.values()]
    assert max(heights) < 60, heights
    edges = {cam: fixed_edge(t.silhouettes, t.boxes, config=CleanupConfig(fixed_rows=0)) for cam, t in tracks.items()}
    assert any(e.sum() >= 15 for e in edges.values()), edges  # the premise: one row, flat, all the window
    assert not any(fixed_edge(t.silhouettes, t.boxes).any() for t in tracks.values())


def _bottoms(frames):
    return np.array([np.flatnonzero(f.any(axis=1))[-1] for f in frames])


def test_a_walker_passing_the_end_of_a_wall_is_cut_only_behind_it(small_model):
    """``wall_end``: a fixed wall that ends in the image, the walker behind it for part of the
    window and whole for the rest. Only the frames that end on the wall's row are taken as
    hidden, each with its own share; the others are whole (share 0, matched whole on the same
    rows as the cut frames), and the growth is read from their heights and the head's path when
    they are half the window, else from the head's width and path (frames astride the wall's end, one
    leg cut, are neither: :func:`estimator.cleanup.astride_edge`). A camera
    that sees fewer than 6 frames behind the wall is left as it is (one here: its walker is astride
    the wall's end on most frames, and its heights take it to the wrong side; docs/ROBUSTNESS.md)."""
    walk = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=3, image_size=(320, 240)))
    sils = damage_sequence(walk.silhouettes, "wall_end", seed=1, truth=walk.truth)
    est = estimate_walk(tracks_from_sequence(Sequence(walk.fps, walk.cameras, walk.image_size, sils, walk.truth)),
                        small_model)
    ref = estimate_walk(tracks_from_sequence(walk), small_model)
    told = 0
    for k, cam in enumerate(walk.cameras):
        c, hidden = est.cameras[cam], est.tracks[cam].hidden
        steady = int(np.random.default_rng([1, k]).integers(2**31))  # damage_sequence's draw of the wall's row
        row = _wall_row(walk.silhouettes[cam], np.random.default_rng([1, k, steady, 1]))
        behind = _bottoms(sils[cam]) == row - 1  # on the wall's row, not astride its end
        if behind.sum() < 6:
            assert not c.cleanup.fixed_edge, cam
            continue
        told += 1
        assert c.cleanup.fixed_edge and np.sum(c.cleanup.on_edge != behind) <= 1, (cam, c.cleanup.on_edge, behind)
        truth = 1.0 - _heights(sils[cam]) / _heights(walk.silhouettes[cam])
        edge = c.cleanup.on_edge
        assert np.all(hidden[~edge] == 0) and np.all(hidden[edge] > 0), cam
        assert np.median(np.abs(hidden - truth)[edge]) <= 0.05, (cam, hidden, truth)
        assert np.sign(c.cue.growth) == np.sign(ref.cameras[cam].cue.growth)
        past = c.cleanup.past_edge()
        assert c.cue.source in (("head width", "head+head width") if past is None else ("head+height",)), \
            (c.cue.source, past)
        assert abs(azimuth_difference_deg(c.viewpoint.azimuth_deg, ref.cameras[cam].viewpoint.azimuth_deg)) <= 12
    assert told >= 1


def test_a_walker_astride_the_end_of_a_wall_is_neither_behind_it_nor_whole():
    """Two legs (crops of 100 x 30 px in the full frame): behind the wall both end on its row; astride
    its end one leg ends there and the other reaches the ground; past it both do. Only the second
    is astride, and the share from the whole frames' heights leaves it out."""
    def frame(left, right):
        s = np.zeros((100, 30), np.uint8)
        s[:50, 5:25] = 255  # head and trunk
        s[50:left, 5:12] = 255
        s[50:right, 18:25] = 255
        return s[:max(left, right)]

    sils = [frame(70, 70)] * 6 + [frame(70, 90)] * 3 + [frame(100, 100)] * 6  # astride: the free foot lifted
    boxes = np.array([[10.0, 20.0, 30.0, s.shape[0]] for s in sils])
    edge = np.array([True] * 6 + [False] * 9)
    astride = astride_edge(sils, boxes, edge)
    assert np.array_equal(astride, [False] * 6 + [True] * 3 + [False] * 6)
    assert abs(edge_share(boxes, edge, whole=~edge & ~astride) - 0.3) < 1e-9  # 70 of 100 rows show
    assert edge_share(boxes, edge) < 0.25  # the astride frames counted as whole: a shorter walker
    assert not astride_edge(sils, boxes, np.zeros(15, bool)).any()


def test_a_walker_behind_a_wall_is_matched_with_a_cache_of_the_cut_models_own(small_model):
    """Overlapping windows of walkers behind a low wall, with a MatchCache: the estimates are those
    without one, and the second window finds the frames it shares with the first in the cache of
    the model cut at their share (:meth:`MatchCache.for_cut`), never in the whole model's."""
    from estimator.matchcache import MatchCache
    from estimator.windows import window_tracks

    seq = synthesize(SynthSpec(n_cameras=2, n_frames=30, seed=5, azimuths=(60.0, 150.0), elevations=(10.0, 10.0),
                               image_size=(320, 240)))
    walled = tracks_from_sequence(Sequence(seq.fps, seq.cameras, seq.image_size,
                                           damage_sequence(seq.silhouettes, "low_wall", seed=0), seq.truth))
    cache = MatchCache()
    for a in (0, 10):
        tracks = window_tracks(walled, a, a + 20)
        plain = estimate_walk(tracks, small_model)
        shares = [plain.cameras[c].cleanup.hidden for c in seq.cameras]
        assert all(s > 0 for s in shares), shares
        cuts = [cache.for_cut(small_model.hidden_below(s)) for s in shares]
        hits = [c.hits for c in cuts]
        cached = estimate_walk(tracks, small_model, cache=cache)
        assert json.dumps(cached.to_result(), default=str) == json.dumps(plain.to_result(), default=str)
        if a:
            assert all(c.hits - h >= 10 for c, h in zip(cuts, hits)), [c.hits - h for c, h in zip(cuts, hits)]
            assert all(c.derived_hits > 0 for c in cuts)
    # The viewpoint votes and phase evidence of the walled cameras are in the cut models' caches only
    # (the whole model's holds the clean-up's scores of the same silhouettes).
    assert not any(t[0] in ("phase", "cell") for e in cache._entries.values() for t in e.derived)
    assert all(any(t[0] == "cell" for e in c._entries.values() for t in e.derived) for c in cuts)
    with pytest.raises(ValueError, match="cut for a walker hidden below"):
        cache.for_cut(small_model)
