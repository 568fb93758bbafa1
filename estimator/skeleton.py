"""The posecal skeleton: body size, joint angles and forward kinematics.

The skeleton has the 13 public joints of DESIGN.md plus the joints needed in
between (pelvis, spine, neck, hands, toes). A pose is given by :class:`GaitAngles`
— segment angles in the walker's heading frame (x forward, y left, z up), the
same quantities the gait model fits to motion capture — and turned into joint
positions by :func:`forward_kinematics` for a body of a given :class:`BodyShape`.

Segment angles are *global* (relative to the vertical in the heading frame), as
gait labs report thigh and shank angles: the sagittal angle ``alpha`` of a
segment pointing from joint a to joint b is ``atan2(dx, -dz)`` (0 = hanging
down, positive = swung forward) and its lateral angle ``beta`` is
``asin(side * dy / |d|)`` (positive = outward, side = +1 left, -1 right).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from .joints import JOINT_NAMES

__all__ = ["FULL_JOINT_NAMES", "BodyShape", "GaitAngles", "forward_kinematics", "segment_angles"]

FULL_JOINT_NAMES: tuple[str, ...] = JOINT_NAMES + (
    "pelvis",
    "spine",
    "neck",
    "left_hand",
    "right_hand",
    "left_toe",
    "right_toe",
)
"""All skeleton joints: the 13 public ones first, then the joints in between."""

J = {name: i for i, name in enumerate(FULL_JOINT_NAMES)}

# Segment lengths as fractions of stature, after Winter, "Biomechanics and Motor
# Control of Human Movement" (segment lengths of Drillis & Contini), adjusted so
# joint centres (not bony landmarks) line up with the CMU skeletons.
_RATIOS = {
    "thigh": 0.245,
    "shank": 0.246,
    "ankle_height": 0.039,
    "foot": 0.105,
    "hip_width": 0.105,
    "pelvis_up": 0.04,
    "trunk": 0.275,
    "shoulder_width": 0.205,
    "shoulder_drop": 0.02,
    "head": 0.105,
    "upper_arm": 0.172,
    "forearm": 0.150,
    "hand": 0.085,
}


@dataclass(frozen=True)
class BodyShape:
    """Size of the walker: stature, limb proportions and girth.

    Parameters
    ----------
    height : float
        Stature in metres (nominal: exact when all proportions are 1).
    leg_length, arm_length, trunk_length : float
        Multipliers of the standard segment lengths (Winter's tables).
    shoulder_width, hip_width : float
        Multipliers of the standard breadths.
    girth : float
        Multiplier of all body-part radii (1 = average build).
    """

    height: float = 1.75
    leg_length: float = 1.0
    arm_length: float = 1.0
    trunk_length: float = 1.0
    shoulder_width: float = 1.0
    hip_width: float = 1.0
    girth: float = 1.0

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not np.isfinite(value) or value <= 0:
                raise ValueError(f"BodyShape.{f.name} must be a positive number, got {value!r}")

    @classmethod
    def random(cls, rng: np.random.Generator | int | None = None) -> "BodyShape":
        """A plausible adult: stature 1.50–1.95 m, proportions within about ±6%."""
        rng = np.random.default_rng(rng)
        return cls(
            height=float(rng.uniform(1.50, 1.95)),
            leg_length=float(rng.uniform(0.94, 1.06)),
            arm_length=float(rng.uniform(0.94, 1.06)),
            trunk_length=float(rng.uniform(0.95, 1.05)),
            shoulder_width=float(rng.uniform(0.92, 1.08)),
            hip_width=float(rng.uniform(0.92, 1.1)),
            girth=float(rng.uniform(0.85, 1.25)),
        )

    def lengths(self) -> dict[str, float]:
        """Segment lengths and breadths in metres."""
        scale = {
            "thigh": self.leg_length,
            "shank": self.leg_length,
            "ankle_height": self.leg_length,
            "trunk": self.trunk_length,
            "shoulder_width": self.shoulder_width,
            "hip_width": self.hip_width,
            "upper_arm": self.arm_length,
            "forearm": self.arm_length,
            "hand": self.arm_length,
        }
        return {k: self.height * r * scale.get(k, 1.0) for k, r in _RATIOS.items()}

    @property
    def hip_height(self) -> float:
        """Height of the hip joints above the ground when standing straight."""
        L = self.lengths()
        return L["ankle_height"] + L["shank"] + L["thigh"]


_ANGLE_NAMES = (
    "thigh", "shank", "foot", "upper_arm", "forearm",  # sagittal, per side
    "thigh_lat", "shank_lat", "upper_arm_lat", "forearm_lat",  # lateral, per side
)  # fmt: skip


@dataclass(frozen=True)
class GaitAngles:
    """Joint angles of T poses (radians) and the pelvis offset (metres).

    Per-side arrays have shape (T, 2): column 0 is the left side, column 1 the
    right. Sagittal angles: ``thigh``, ``shank``, ``foot`` (the foot's angle from
    the downward vertical, about pi/2 when flat), ``upper_arm``, ``forearm``.
    Lateral angles (outward positive): ``thigh_lat``, ``shank_lat``,
    ``upper_arm_lat``, ``forearm_lat``. Body: ``pelvis_yaw`` and
    ``pelvis_obliquity`` (rotation about z and x of the hip line),
    ``thorax_yaw``, ``lean`` (forward tilt of the trunk), and the offset of the
    hip centre, ``sway`` (y) and ``bounce`` (z minus standing hip height), both
    as fractions of the standing hip height, each (T,).
    """

    thigh: np.ndarray
    shank: np.ndarray
    foot: np.ndarray
    upper_arm: np.ndarray
    forearm: np.ndarray
    thigh_lat: np.ndarray
    shank_lat: np.ndarray
    upper_arm_lat: np.ndarray
    forearm_lat: np.ndarray
    pelvis_yaw: np.ndarray
    pelvis_obliquity: np.ndarray
    thorax_yaw: np.ndarray
    lean: np.ndarray
    sway: np.ndarray
    bounce: np.ndarray
    extra: dict = field(default_factory=dict, compare=False)

    def __len__(self) -> int:
        return len(self.lean)

    def __post_init__(self) -> None:
        T = len(self.lean)
        for f in fields(self):
            if f.name == "extra":
                continue
            value = np.asarray(getattr(self, f.name), dtype=float)
            expected = (T, 2) if f.name in _ANGLE_NAMES else (T,)
            if value.shape != expected:
                raise ValueError(f"GaitAngles.{f.name} must have shape {expected}, got {value.shape}")
            object.__setattr__(self, f.name, value)


_SIDE = np.array([1.0, -1.0])  # left, right: sign of y


def _direction(alpha: np.ndarray, beta: np.ndarray) -> np.ndarray:
    """Unit vectors with sagittal angle alpha and lateral angle beta, shape (T, 2, 3)."""
    cb = np.cos(beta)
    return np.stack([np.sin(alpha) * cb, _SIDE * np.sin(beta), -np.cos(alpha) * cb], axis=-1)


def _zx_rotate(yaw: np.ndarray, roll: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors v (T, K, 3) by R_z(yaw) R_x(roll), angles of shape (T,)."""
    cy, sy = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    cr, sr = np.cos(roll)[:, None], np.sin(roll)[:, None]
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    y, z = cr * y - sr * z, sr * y + cr * z
    return np.stack([cy * x - sy * y, sy * x + cy * y, z], axis=-1)


def forward_kinematics(angles: GaitAngles, shape: BodyShape) -> np.ndarray:
    """Joint positions of T poses in the heading frame, shape (T, 20, 3).

    The origin is on the ground below the pelvis's mean path: x forward, y left,
    z up. Order: :data:`FULL_JOINT_NAMES`.
    """
    L = shape.lengths()
    T = len(angles)
    out = np.empty((T, len(FULL_JOINT_NAMES), 3))
    zeros = np.zeros(T)
    h = shape.hip_height
    hip_centre = np.stack([zeros, angles.sway * h, h * (1.0 + angles.bounce)], -1)
    half_hips = np.array([[0.0, L["hip_width"] / 2, 0.0], [0.0, -L["hip_width"] / 2, 0.0]])
    hips = hip_centre[:, None] + _zx_rotate(angles.pelvis_yaw, angles.pelvis_obliquity, np.broadcast_to(half_hips, (T, 2, 3)))
    knees = hips + L["thigh"] * _direction(angles.thigh, angles.thigh_lat)
    ankles = knees + L["shank"] * _direction(angles.shank, angles.shank_lat)
    toes = ankles + L["foot"] * _direction(angles.foot, np.zeros((T, 2)))
    pelvis = hip_centre + np.array([0.0, 0.0, L["pelvis_up"]])
    trunk_dir = np.stack([np.sin(angles.lean), zeros, np.cos(angles.lean)], -1)
    neck = pelvis + L["trunk"] * trunk_dir
    spine = pelvis + 0.5 * L["trunk"] * trunk_dir
    head = neck + L["head"] * trunk_dir
    half_shoulders = np.array([[0.0, L["shoulder_width"] / 2, -L["shoulder_drop"]], [0.0, -L["shoulder_width"] / 2, -L["shoulder_drop"]]])
    shoulders = neck[:, None] + _zx_rotate(angles.thorax_yaw, zeros, np.broadcast_to(half_shoulders, (T, 2, 3)))
    elbows = shoulders + L["upper_arm"] * _direction(angles.upper_arm, angles.upper_arm_lat)
    fore = _direction(angles.forearm, angles.forearm_lat)
    wrists = elbows + L["forearm"] * fore
    hands = wrists + L["hand"] * fore
    for name, value in (
        ("head", head), ("pelvis", pelvis), ("spine", spine), ("neck", neck),
    ):  # fmt: skip
        out[:, J[name]] = value
    for side, k in (("left", 0), ("right", 1)):
        for name, value in (
            ("shoulder", shoulders), ("elbow", elbows), ("wrist", wrists), ("hand", hands),
            ("hip", hips), ("knee", knees), ("ankle", ankles), ("toe", toes),
        ):  # fmt: skip
            out[:, J[f"{side}_{name}"]] = value[:, k]
    return out


def _sagittal_lateral(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sagittal and lateral angles of the segments a -> b, arrays (T, 2, 3) -> (T, 2)."""
    d = b - a
    alpha = np.arctan2(d[..., 0], -d[..., 2])
    beta = np.arcsin(np.clip(_SIDE * d[..., 1] / np.linalg.norm(d, axis=-1), -1.0, 1.0))
    return alpha, beta


def segment_angles(positions: np.ndarray, standing_hip_height: float) -> GaitAngles:
    """The inverse of :func:`forward_kinematics`: angles of recorded poses.

    Parameters
    ----------
    positions : ndarray of shape (T, 20, 3)
        Joint positions in the heading frame (x forward, y left, z up), with the
        ground at z = 0 and the pelvis's smoothed path at x = y = 0.
    standing_hip_height : float
        The subject's hip height standing, to express ``bounce`` relative to it.
    """
    P = np.asarray(positions, dtype=float)

    def pair(name: str) -> np.ndarray:
        return P[:, [J[f"left_{name}"], J[f"right_{name}"]]]

    hips, knees, ankles, toes = pair("hip"), pair("knee"), pair("ankle"), pair("toe")
    shoulders, elbows, wrists = pair("shoulder"), pair("elbow"), pair("wrist")
    thigh, thigh_lat = _sagittal_lateral(hips, knees)
    shank, shank_lat = _sagittal_lateral(knees, ankles)
    foot, _ = _sagittal_lateral(ankles, toes)
    upper_arm, upper_arm_lat = _sagittal_lateral(shoulders, elbows)
    forearm, forearm_lat = _sagittal_lateral(elbows, wrists)
    hip_line = hips[:, 0] - hips[:, 1]
    shoulder_line = shoulders[:, 0] - shoulders[:, 1]
    hip_centre = hips.mean(axis=1)
    trunk = P[:, J["neck"]] - P[:, J["pelvis"]]
    return GaitAngles(
        thigh=thigh,
        shank=shank,
        foot=foot,
        upper_arm=upper_arm,
        forearm=forearm,
        thigh_lat=thigh_lat,
        shank_lat=shank_lat,
        upper_arm_lat=upper_arm_lat,
        forearm_lat=forearm_lat,
        pelvis_yaw=np.arctan2(-hip_line[:, 0], hip_line[:, 1]),
        pelvis_obliquity=np.arctan2(hip_line[:, 2], np.linalg.norm(hip_line[:, :2], axis=1)),
        thorax_yaw=np.arctan2(-shoulder_line[:, 0], shoulder_line[:, 1]),
        lean=np.arctan2(trunk[:, 0], trunk[:, 2]),
        sway=hip_centre[:, 1] / standing_hip_height,
        bounce=(hip_centre[:, 2] - standing_hip_height) / standing_hip_height,
    )
