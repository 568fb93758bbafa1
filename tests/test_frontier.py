"""Pinhole cameras refined on the silhouettes' epipolar tangents (estimator.frontier), on real renders."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from estimator._selfcal_core import geodesic_deg
from estimator.camera import world_to_camera_rotation
from estimator.damage import damage_sequence
from estimator.frontier import FrontierConfig, outlines, paired, refine_on_tangents, tangent_residuals
from estimator.perspective import perspective_refine
from estimator.pinhole import PinholeCameras
from estimator.selfcal import RIGID_LINKS, self_calibrate
from estimator.sequence import Sequence
from estimator.pipeline import tracks_from_sequence
from estimator.synth import SynthSpec, synthesize


@pytest.fixture(scope="module")
def rendered():
    """Three cameras on a rendered walk, their outlines and the true cameras in camera 0's frame."""
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=5, azimuths=(30.0, 100.0, 215.0),
                               elevations=(5.0, 20.0, 10.0)))
    tracks = tracks_from_sequence(seq)
    shapes = [outlines(tracks[c].silhouettes, tracks[c].boxes, tracks[c].image_size) for c in seq.cameras]
    cams = [seq.truth["cameras"][c] for c in seq.cameras]
    world = np.array([world_to_camera_rotation(c["azimuth_deg"], c["elevation_deg"]) for c in cams])
    rotations = world @ world[0].T
    centres = (np.array([c["position_m"] for c in cams]) - cams[0]["position_m"]) @ world[0].T
    focal = np.array([c["focal_px"] for c in cams])
    principal = np.tile((np.array(seq.image_size, float) - 1) / 2, (3, 1))
    joints2d = np.stack([[f["joints2d"][c] for f in seq.truth["frames"]] for c in seq.cameras]).astype(float)
    return shapes, rotations, centres, focal, principal, joints2d, seq.image_size


def _residuals(shapes, rotations, centres, focal, principal):
    pairs = np.array([(0, 1), (0, 2), (1, 2)])
    k = PinholeCameras.from_centres(focal, principal, rotations, centres).matrices
    return tangent_residuals(k, rotations, centres, paired(shapes, pairs), pairs)


def test_outlines_are_hulls_in_the_full_frame(rendered):
    shapes = rendered[0]
    assert all(s.valid.all() for s in shapes)  # the synthetic walker stays clear of the border
    v = shapes[0].vertices
    assert v.shape[0] == 30 and v.shape[2] == 2
    assert (v[..., 0] > 0).all() and (v[..., 0] < 640).all() and (v[..., 1] > 0).all() and (v[..., 1] < 480).all()
    # A silhouette touching the border has no outline (the border would make its tangents).
    sil = np.ones((10, 6), np.uint8)
    out = outlines([sil, sil, None], np.array([[0, 50, 6, 10], [100, 50, 6, 10], [np.nan] * 4]), (640, 480))
    assert out.valid.tolist() == [False, True, False]
    # On a frame the clean-up cut below the feet, the vertices on the cut (the crop's bottom) are loose.
    cut = outlines([sil, sil], np.array([[100, 50, 6, 10]] * 2), (640, 480), cut=[False, True])
    assert cut.valid.all() and not cut.loose[0].any()
    assert np.array_equal(cut.loose[1], cut.vertices[1, :, 1] > 59.5 - 1.0 - 0.1 * 10) and cut.loose[1].sum() >= 2
    # The hull of the pixels' corners: a 6 x 10 block spans 6 x 10 pixels, not 5 x 9.
    box = out.vertices[1]
    assert np.ptp(box[:, 0]) == 6.0 and np.ptp(box[:, 1]) == 10.0


def test_the_true_cameras_meet_the_tangents(rendered):
    shapes, rotations, centres, focal, principal = rendered[:5]
    res, ok = _residuals(shapes, rotations, centres, focal, principal)
    assert ok.sum() >= 30
    assert np.median(np.abs(res[ok])) < 0.5  # pixel quantisation
    turned = rotations.copy()
    turned[1] = Rotation.from_euler("y", 3.0, degrees=True).as_matrix() @ rotations[1]
    bad, ok2 = _residuals(shapes, turned, centres, focal, principal)
    assert np.median(np.abs(bad[ok2])) > 4 * np.median(np.abs(res[ok]))


@pytest.fixture(scope="module")
def pinhole(rendered):
    """As in the rig from silhouettes: pinhole cameras adjusted to 2D joints with errors of their own per
    camera and joint (a measured posture's systematic part), degrees off."""
    joints2d, image_size = rendered[5:]
    rng = np.random.default_rng(0)
    biased = joints2d + rng.normal(0.0, 4.0, (3, 1, joints2d.shape[2], 2)) + rng.normal(0.0, 1.0, joints2d.shape)
    cal = self_calibrate(biased, refine=True, upright=True)
    return perspective_refine(biased, np.tile(image_size, (3, 1)), cal.rotations, cal.scales, list(RIGID_LINKS))


def test_refining_on_tangents_undoes_the_joints_systematic_errors(rendered, pinhole):
    """The pinhole cameras on biased joints are degrees off; the tangents bring them back."""
    shapes, rotations, centres, focal = rendered[:4]
    pin = pinhole
    found = refine_on_tangents(pin.focal_px, pin.principal_px, pin.rotations, pin.centres, shapes)
    assert found is not None and found.pairs == [(0, 1), (0, 2), (1, 2)] and found.frames >= 30
    before = [geodesic_deg(a, b) for a, b in zip(pin.rotations[1:], rotations[1:])]
    after = [geodesic_deg(a, b) for a, b in zip(found.rotations[1:], rotations[1:])]
    assert max(after) < 1.0 and max(after) < 0.5 * max(before), (before, after)
    assert found.residual_px[1] < 0.5 < found.residual_px[0]
    focal_error = np.abs(np.log(found.focal_px / focal))
    assert focal_error.max() < 0.1 and focal_error.max() < np.abs(np.log(pin.focal_px / focal)).max()
    assert np.allclose(found.rotations[0], np.eye(3)) and np.allclose(found.centres[0], 0.0)
    assert np.isclose(np.linalg.norm(found.centres[1]), np.linalg.norm(pin.centres[1]), rtol=1e-3)  # the gauge


def test_outlines_with_a_limb_cut_off_are_set_aside(pinhole):
    """A segmenter that loses a forearm or a shin (and the foot with it) on every frame moves the lowest
    tangent by tens of pixels on half the frames: the soft-L1 adjustment follows them further off than it
    started, the default's second, Cauchy stage sets those frames aside."""
    seq = synthesize(SynthSpec(n_cameras=3, n_frames=30, seed=5, azimuths=(30.0, 100.0, 215.0),
                               elevations=(5.0, 20.0, 10.0)))
    cut = Sequence(seq.fps, seq.cameras, seq.image_size,
                   damage_sequence(seq.silhouettes, "cut_limb", seed=1, truth=seq.truth), seq.truth)
    tracks = tracks_from_sequence(cut)
    shapes = [outlines(tracks[c].silhouettes, tracks[c].boxes, tracks[c].image_size) for c in seq.cameras]
    world = np.array([world_to_camera_rotation(seq.truth["cameras"][c]["azimuth_deg"],
                                               seq.truth["cameras"][c]["elevation_deg"]) for c in seq.cameras])
    truth = world @ world[0].T

    def worst(config: FrontierConfig) -> float:
        found = refine_on_tangents(pinhole.focal_px, pinhole.principal_px, pinhole.rotations, pinhole.centres,
                                   shapes, config)
        return max(geodesic_deg(a, b) for a, b in zip(found.rotations[1:], truth[1:]))

    start = max(geodesic_deg(a, b) for a, b in zip(pinhole.rotations[1:], truth[1:]))
    soft = worst(FrontierConfig(losses=("soft_l1",)))
    default = worst(FrontierConfig())
    assert FrontierConfig().losses == ("soft_l1", "cauchy")
    assert soft > start and default < start and default < 0.5 * soft, (start, soft, default)  # 2.6: 6.7, 2.1


def test_directions_the_tangents_hardly_see_are_held(rendered, pinhole):
    """Rotation directions whose posterior is wider than ``hold_std_deg`` stay where they started: with
    every direction counted as weak (0 deg) and held stiffly the cameras keep the pinhole rig's rotations (to a
    small fraction of the 2-3 deg the free adjustment moves them), while the focal lengths still move."""
    shapes = rendered[0]
    free = refine_on_tangents(pinhole.focal_px, pinhole.principal_px, pinhole.rotations, pinhole.centres, shapes)
    held = refine_on_tangents(pinhole.focal_px, pinhole.principal_px, pinhole.rotations, pinhole.centres, shapes,
                              FrontierConfig(hold_std_deg=0.0, hold_px_per_deg=1000.0))
    assert free.held == 0 and held.held == 6  # 3 rotation directions per camera beside the reference
    np.testing.assert_allclose(held.rotation_std_deg, free.rotation_std_deg)  # the tangents' posterior, unheld
    moved_free = max(geodesic_deg(a, b) for a, b in zip(free.rotations, pinhole.rotations))
    moved_held = max(geodesic_deg(a, b) for a, b in zip(held.rotations, pinhole.rotations))
    assert moved_free > 1.0 and moved_held < 0.1 * moved_free, (moved_free, moved_held)
    assert not np.allclose(held.focal_px, pinhole.focal_px)


def test_too_few_frames_with_tangents_give_none(rendered):
    shapes, rotations, centres, focal, principal = rendered[:5]
    few = [type(s)(s.vertices, s.valid & (np.arange(len(s.valid)) < 5), s.loose) for s in shapes]
    assert refine_on_tangents(focal, principal, rotations, centres, few, FrontierConfig(min_frames=8)) is None


def test_a_camera_in_no_pair_with_tangents_is_held_not_fatal(rendered, pinhole):
    """Camera 2's outlines are all lost (a segmenter that never found the walker there): the pair (0, 1)
    still refines, camera 2 stays where its priors hold it (the Jacobian once failed on its empty pairs)."""
    shapes = list(rendered[0])
    rotations = rendered[1]
    shapes[2] = type(shapes[2])(shapes[2].vertices, np.zeros_like(shapes[2].valid), shapes[2].loose)
    found = refine_on_tangents(pinhole.focal_px, pinhole.principal_px, pinhole.rotations, pinhole.centres, shapes)
    assert found is not None and found.pairs == [(0, 1)]
    assert geodesic_deg(found.rotations[1], rotations[1]) < geodesic_deg(pinhole.rotations[1], rotations[1])
    assert geodesic_deg(found.rotations[2], pinhole.rotations[2]) < 0.5


def test_a_refinement_left_without_tangents_reports_null_not_nan():
    """When the adjusted cameras leave no outline pair to measure, the final residual is infinite, and the
    result's summary says null (a NaN there once stopped `posecal estimate` from writing JSON)."""
    import json

    from estimator.frontier import _median_abs
    from estimator.rig import _num

    assert _median_abs(np.array([])) == np.inf and _median_abs(np.array([-2.0, 1.0, 3.0])) == 2.0
    summary = {"residual_px": [_num(1.23456, 3), _num(_median_abs(np.array([])), 3)]}
    assert json.loads(json.dumps(summary, allow_nan=False)) == {"residual_px": [1.235, None]}
