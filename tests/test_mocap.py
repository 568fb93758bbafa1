"""ASF/AMC and BVH readers agree on the same CMU trial; person frame conventions."""

import os

import numpy as np
import pytest

from estimator.joints import JOINT_INDEX
from estimator.mocap import read_motion


@pytest.fixture(scope="module")
def trial(mocap_dir):
    return read_motion(os.path.join(mocap_dir, "16_15.amc")), read_motion(os.path.join(mocap_dir, "16_15.bvh"))


def test_readers_agree(trial):
    amc, bvh = trial
    assert len(amc) == len(bvh) == 471
    assert amc.fps == pytest.approx(120.0) and bvh.fps == pytest.approx(120.0, rel=1e-4)
    d = np.linalg.norm(amc.joints - bvh.joints, axis=-1)
    # Same motion: legs and trunk within 2 cm on (almost) every frame.
    assert np.percentile(d, 95) < 0.02, np.percentile(d, 95, axis=0)


def test_metric_units_and_z_up(trial):
    amc, _ = trial
    stature = np.ptp(amc.positions[0, :, 2])
    assert 1.4 < stature < 2.0
    j = amc.joints
    assert np.all(j[:, JOINT_INDEX["head"], 2] > j[:, JOINT_INDEX["left_knee"], 2])


def test_person_frame(trial):
    amc, _ = trial
    pf = amc.person_frame()[:, :13]
    np.testing.assert_allclose(pf.mean(axis=1), 0.0, atol=1e-9)
    # Left joints are on +y (the walker's left), over the whole walk.
    assert np.median(pf[:, JOINT_INDEX["left_hip"], 1] - pf[:, JOINT_INDEX["right_hip"], 1]) > 0.1
    # Walking along +x: the head moves forward in the heading frame's world path.
    h = amc.heading()
    assert np.ptp(np.unwrap(h)) < np.radians(40)  # a straight walk


def test_unknown_format_rejected(tmp_path):
    p = tmp_path / "walk.c3d"
    p.write_text("x")
    with pytest.raises(ValueError, match="unknown motion format"):
        read_motion(p)
