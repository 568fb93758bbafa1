"""Gait model: periodic, mirror-symmetric, fitted to the CMU walks."""

import os

import numpy as np
import pytest

from estimator.gait import GaitStyle, fit_gait, heel_strikes, load_gait, motion_phase
from estimator.joints import MIRROR, N_JOINTS
from estimator.mocap import read_motion
from estimator.skeleton import BodyShape, forward_kinematics

PHASES = np.linspace(0, 1, 40, endpoint=False)


def joints(phase, style=None, shape=None):
    return forward_kinematics(load_gait().angles(phase, style), shape or BodyShape())[:, :N_JOINTS]


def test_gait_is_periodic():
    np.testing.assert_allclose(joints(PHASES), joints(PHASES + 1.0), atol=1e-12)
    np.testing.assert_allclose(joints(PHASES), joints(PHASES - 3.0), atol=1e-12)


@pytest.mark.parametrize("style", [GaitStyle(), GaitStyle(stride=1.2, leg_lift=0.8, arm_swing=1.4, cadence=1.0)])
def test_half_cycle_mirrors_left_and_right(style):
    a, b = joints(PHASES, style), joints(PHASES + 0.5, style)
    mirrored = a[:, list(MIRROR)] * np.array([1.0, -1.0, 1.0])
    np.testing.assert_allclose(b, mirrored, atol=1e-9)
    # ... and the pose really changes over half a cycle (not trivially symmetric).
    assert np.abs(a - b).max() > 0.2


def test_phase_zero_is_right_heel_strike():
    p = joints(np.array([0.0, 0.5]))
    right, left = 12, 11  # ankles
    assert p[0, right, 0] - p[0, left, 0] > 0.3  # right foot in front at phase 0
    assert p[1, left, 0] - p[1, right, 0] > 0.3


def test_style_scales_the_motion():
    base = joints(PHASES)
    arms = joints(PHASES, GaitStyle(arm_swing=1.5))
    wrist_range = lambda j: np.ptp(j[:, 5, 0])  # noqa: E731 - left wrist, forward travel
    assert wrist_range(arms) > 1.3 * wrist_range(base)
    lift = joints(PHASES, GaitStyle(leg_lift=1.3))
    ankle_height = lambda j: (j[:, 11, 2] - j[:, :, 2].min(axis=1)).max()  # noqa: E731
    assert ankle_height(lift) > ankle_height(base) + 0.01
    stride = joints(PHASES, GaitStyle(stride=1.2))
    step = lambda j: j[0, 12, 0] - j[0, 11, 0]  # noqa: E731
    assert step(stride) > 1.1 * step(base)


def test_heel_strikes_alternate(mocap_dir):
    m = read_motion(os.path.join(mocap_dir, "16_15.amc"))
    P = m.heading_frame()
    right, left = heel_strikes(P, "right"), heel_strikes(P, "left")
    assert len(right) >= 2 and len(left) >= 2
    events = sorted([(t, "r") for t in right] + [(t, "l") for t in left])
    sides = [s for _, s in events]
    assert all(a != b for a, b in zip(sides, sides[1:])), events
    phase = motion_phase(m)
    # Left heel strikes fall near the middle of the right-heel-strike cycle.
    lphase = np.interp(left, np.arange(len(phase)), phase)
    assert np.all(np.abs(lphase - 0.5) < 0.08), lphase


def test_shipped_fit_is_reproducible(mocap_dir):
    motions = [read_motion(os.path.join(mocap_dir, f)) for f in ("16_15.amc", "07_05.amc")]
    fitted, shipped = fit_gait(motions), load_gait()
    assert fitted.harmonics == shipped.harmonics
    for name, coef in shipped.coefficients.items():
        np.testing.assert_allclose(fitted.coefficients[name], coef, atol=1e-9, err_msg=name)


def test_fit_matches_recorded_knee_flexion(mocap_dir):
    m = read_motion(os.path.join(mocap_dir, "07_05.amc"))
    from estimator.gait import motion_angles

    rec = motion_angles(m)
    model = load_gait()
    phase = motion_phase(m)
    knee_rec = np.degrees(rec.thigh[:, 1] - rec.shank[:, 1])
    knee_fit = np.degrees(model.curve("thigh", phase) - model.curve("shank", phase))
    assert np.median(np.abs(knee_rec - knee_fit)) < 5.0
    assert 50 < knee_fit.max() < 75  # swing-phase peak knee flexion of a normal walk


def test_bad_style_rejected():
    with pytest.raises(ValueError, match="stride"):
        GaitStyle(stride=-1)
    with pytest.raises(ValueError, match="cadence"):
        GaitStyle(cadence=0)
