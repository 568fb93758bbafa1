"""A closed mesh of the walking body: tapered capsules attached to the bones.

Each body part is the convex hull of two (elliptical) spheres placed along one
bone of the skeleton — a sphere-swept cone, closed and watertight. Parts are
built once per :class:`~estimator.skeleton.BodyShape` in their own local frame;
:func:`part_transforms` gives the rigid transform of every part for a pose, so
a renderer moves nodes instead of rebuilding meshes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh

from .skeleton import FULL_JOINT_NAMES, BodyShape

__all__ = ["BodyPart", "PARTS", "part_meshes", "part_transforms"]

_J = {name: i for i, name in enumerate(FULL_JOINT_NAMES)}


@dataclass(frozen=True)
class BodyPart:
    """One tapered capsule.

    The capsule's axis runs from ``a + t0 (b - a)`` to ``a + t1 (b - a)`` with
    radii ``r0``, ``r1`` (fractions of stature, times the body's girth); its
    cross-section is ``depth`` times as deep (x) as it is wide (y). The width
    axis follows the line ``lateral`` (a pair of joints) where given, else the
    walker's left.
    """

    name: str
    a: str
    b: str
    r0: float
    r1: float
    t0: float = 0.0
    t1: float = 1.0
    depth: float = 1.0
    lateral: tuple[str, str] | None = None


PARTS: tuple[BodyPart, ...] = (
    BodyPart("head", "neck", "head", 0.055, 0.05, t0=0.72, t1=1.28, depth=1.15),
    BodyPart("neck", "neck", "head", 0.03, 0.03, t0=0.0, t1=0.6),
    BodyPart("chest", "spine", "neck", 0.088, 0.092, t0=-0.1, t1=0.82, depth=0.62, lateral=("left_shoulder", "right_shoulder")),
    BodyPart("abdomen", "pelvis", "spine", 0.085, 0.08, t0=-0.25, t1=1.0, depth=0.66, lateral=("left_hip", "right_hip")),
    BodyPart("hips", "left_hip", "right_hip", 0.058, 0.058, t0=-0.2, t1=1.2),
    BodyPart("shoulders", "left_shoulder", "right_shoulder", 0.034, 0.034, t0=-0.02, t1=1.02),
    BodyPart("left_upper_arm", "left_shoulder", "left_elbow", 0.032, 0.027),
    BodyPart("right_upper_arm", "right_shoulder", "right_elbow", 0.032, 0.027),
    BodyPart("left_forearm", "left_elbow", "left_wrist", 0.026, 0.019),
    BodyPart("right_forearm", "right_elbow", "right_wrist", 0.026, 0.019),
    BodyPart("left_hand", "left_wrist", "left_hand", 0.02, 0.017, t1=0.85, depth=0.6),
    BodyPart("right_hand", "right_wrist", "right_hand", 0.02, 0.017, t1=0.85, depth=0.6),
    BodyPart("left_thigh", "left_hip", "left_knee", 0.056, 0.037),
    BodyPart("right_thigh", "right_hip", "right_knee", 0.056, 0.037),
    BodyPart("left_shin", "left_knee", "left_ankle", 0.036, 0.023),
    BodyPart("right_shin", "right_knee", "right_ankle", 0.036, 0.023),
    BodyPart("left_foot", "left_ankle", "left_toe", 0.024, 0.02, t0=-0.25, t1=1.0),
    BodyPart("right_foot", "right_ankle", "right_toe", 0.024, 0.02, t0=-0.25, t1=1.0),
)
"""The body parts, in rendering order."""

_A = np.array([_J[p.a] for p in PARTS])
_B = np.array([_J[p.b] for p in PARTS])
_T0 = np.array([p.t0 for p in PARTS])
_T1 = np.array([p.t1 for p in PARTS])
_LAT = np.array([[_J[p.lateral[0]], _J[p.lateral[1]]] if p.lateral else [-1, -1] for p in PARTS])


def _unit_sphere() -> np.ndarray:
    return trimesh.creation.icosphere(subdivisions=1).vertices


def part_meshes(shape: BodyShape, bone_lengths: np.ndarray) -> list[trimesh.Trimesh]:
    """Meshes of all parts in their local frames (z along the bone, from 0).

    Parameters
    ----------
    shape : BodyShape
    bone_lengths : ndarray of shape (P,)
        Length of each part's bone ``|b - a|`` for this body (constant over a walk).
    """
    sphere = _unit_sphere()
    meshes = []
    for part, length in zip(PARTS, bone_lengths):
        r0, r1 = (part.r0 * shape.height * shape.girth, part.r1 * shape.height * shape.girth)
        ends = []
        for r, t in ((r0, 0.0), (r1, (part.t1 - part.t0) * length)):
            ends.append(sphere * np.array([r * part.depth, r, r]) + np.array([0.0, 0.0, t]))
        meshes.append(trimesh.convex.convex_hull(np.concatenate(ends)))
    return meshes


def bone_lengths(joints: np.ndarray) -> np.ndarray:
    """Length of every part's bone, shape (P,), from one pose (20, 3)."""
    return np.linalg.norm(joints[_B] - joints[_A], axis=-1)


def part_transforms(joints: np.ndarray) -> np.ndarray:
    """Rigid local-to-world transforms of all parts for poses, shape (..., P, 4, 4).

    Parameters
    ----------
    joints : ndarray of shape (..., 20, 3)
        Skeleton joint positions (:data:`~estimator.skeleton.FULL_JOINT_NAMES`).
    """
    joints = np.asarray(joints, dtype=float)
    a, b = joints[..., _A, :], joints[..., _B, :]
    axis = b - a
    z = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
    origin = a + _T0[:, None] * axis
    lateral = np.where(
        (_LAT[:, 0] >= 0)[:, None],
        joints[..., np.maximum(_LAT[:, 0], 0), :] - joints[..., np.maximum(_LAT[:, 1], 0), :],
        np.array([0.0, 1.0, 0.0]),
    )
    # y: the lateral direction made orthogonal to z; fall back to x for bones along it.
    y = lateral - np.sum(lateral * z, axis=-1, keepdims=True) * z
    norm = np.linalg.norm(y, axis=-1, keepdims=True)
    fallback = np.cross(z, np.array([1.0, 0.0, 0.0]))
    y = np.where(norm > 1e-6, y / np.maximum(norm, 1e-12), fallback / np.linalg.norm(fallback, axis=-1, keepdims=True).clip(1e-12))
    x = np.cross(y, z)
    out = np.zeros(joints.shape[:-2] + (len(PARTS), 4, 4))
    out[..., :3, 0], out[..., :3, 1], out[..., :3, 2], out[..., :3, 3] = x, y, z, origin
    out[..., 3, 3] = 1.0
    return out
