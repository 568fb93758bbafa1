"""Body mesh, camera convention and pyrender silhouettes (real EGL renders)."""

import numpy as np
import pytest

from estimator.body import bone_lengths, part_meshes, part_transforms
from estimator.camera import Camera
from estimator.gait import load_gait
from estimator.joints import JOINT_INDEX
from estimator.render import Renderer
from estimator.skeleton import BodyShape, forward_kinematics

SHAPE = BodyShape(height=1.7)


@pytest.fixture(scope="module")
def poses():
    return forward_kinematics(load_gait().angles(np.linspace(0, 1, 8, endpoint=False)), SHAPE)


@pytest.fixture(scope="module")
def renderer():
    with Renderer(SHAPE) as r:
        yield r


def centred(pose, **kw):
    return Camera(target=tuple(pose[:13].mean(0)), **kw)


def test_parts_are_closed_meshes(poses):
    meshes = part_meshes(SHAPE, bone_lengths(poses[0]))
    assert all(m.is_watertight and m.is_volume for m in meshes)
    T = part_transforms(poses)
    R = T[..., :3, :3]
    np.testing.assert_allclose(R @ np.swapaxes(R, -1, -2), np.broadcast_to(np.eye(3), R.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)
    # Bones are rigid over the walk: the meshes built once fit every pose.
    np.testing.assert_allclose(bone_lengths(poses[3]), bone_lengths(poses[0]), atol=1e-9)


@pytest.mark.parametrize("az", [0, 45, 90, 200, 300])
@pytest.mark.parametrize("el", [-15, 10, 35])
def test_joints_fall_inside_silhouettes(renderer, poses, az, el):
    for pose in poses[::3]:
        sil, j2d = renderer.render(pose, centred(pose, azimuth_deg=az, elevation_deg=el, distance=8, focal_px=900))
        uv = np.round(j2d).astype(int)
        assert sil.dtype == np.uint8 and set(np.unique(sil)) <= {0, 255}
        assert np.all(sil[uv[:, 1], uv[:, 0]] == 255), (az, el)


def test_silhouette_matches_projection(renderer, poses):
    """Rendered pixels and numpy projections agree: silhouette bbox vs projected mesh."""
    pose = poses[2]
    cam = centred(pose, azimuth_deg=70, elevation_deg=5, distance=6, focal_px=700)
    sil, _ = renderer.render(pose, cam)
    verts = np.concatenate(
        [m.vertices @ T[:3, :3].T + T[:3, 3] for m, T in zip(part_meshes(SHAPE, bone_lengths(pose)), part_transforms(pose))]
    )
    uv = cam.project(verts)
    vs, us = np.nonzero(sil)
    assert abs(us.min() - uv[:, 0].min()) < 1.5 and abs(us.max() - uv[:, 0].max()) < 1.5
    assert abs(vs.min() - uv[:, 1].min()) < 1.5 and abs(vs.max() - uv[:, 1].max()) < 1.5


def test_azimuth_convention(renderer, poses):
    """A camera at azimuth 90 sees the walker's left side, heading towards the image's left."""
    pose = poses[0]
    cam = centred(pose, azimuth_deg=90, elevation_deg=0)
    uv = cam.project(pose[:13])
    p_left, p_right = cam.rotation[2] @ (pose[JOINT_INDEX["left_hip"]] - cam.position), cam.rotation[2] @ (
        pose[JOINT_INDEX["right_hip"]] - cam.position
    )
    assert p_left < p_right  # left hip nearer the camera
    ahead = cam.project(pose[:13] + np.array([1.0, 0.0, 0.0]))  # the walker one metre further on
    assert np.all(ahead[:, 0] < uv[:, 0] - 50)
    # Azimuth 0: the walker approaches; their left appears on the image's right.
    front = centred(pose, azimuth_deg=0, elevation_deg=0)
    uvf = front.project(pose[:13])
    assert uvf[JOINT_INDEX["left_shoulder"], 0] > uvf[JOINT_INDEX["right_shoulder"], 0]
    # Image v points down: the head is above the ankles.
    assert uv[JOINT_INDEX["head"], 1] < uv[JOINT_INDEX["left_ankle"], 1]


def test_orthographic_render(renderer, poses):
    pose = poses[1]
    cam = centred(pose, azimuth_deg=120, elevation_deg=20, orthographic=True, focal_px=100, image_size=(160, 320))
    sil, j2d = renderer.render(pose, cam)
    assert sil.shape == (320, 160)
    height_px = np.ptp(np.nonzero(sil)[0])
    assert 0.8 * 100 * 1.7 < height_px / np.cos(np.radians(20)) * 1.0 + 40  # body about 1.6 m tall at 100 px/m
    uv = np.round(j2d).astype(int)
    assert np.all(sil[uv[:, 1], uv[:, 0]] == 255)


def test_set_shape_rebuilds_body(poses):
    with Renderer(SHAPE, image_size=(320, 240)) as r:
        cam = centred(poses[0], azimuth_deg=90, elevation_deg=0, distance=8, focal_px=300, image_size=(320, 240))
        thin = r.render(poses[0], cam)[0]
        r.set_shape(BodyShape(height=1.7, girth=1.4))
        wide = r.render(poses[0], cam)[0]
    assert (wide > 0).sum() > 1.2 * (thin > 0).sum()


def test_bad_camera_rejected():
    with pytest.raises(ValueError, match="elevation"):
        Camera(0, 95)
    with pytest.raises(ValueError, match="image_size"):
        Camera(0, 0, image_size=(0, 10))


def test_closing_one_renderer_keeps_others_working(poses):
    cam = centred(poses[0], azimuth_deg=30, elevation_deg=0, distance=8, focal_px=300, image_size=(160, 120))
    with Renderer(SHAPE, image_size=(160, 120)) as a:
        before = a.render(poses[0], cam)[0]
        Renderer(SHAPE, image_size=(160, 120)).close()
        np.testing.assert_array_equal(a.render(poses[0], cam)[0], before)
