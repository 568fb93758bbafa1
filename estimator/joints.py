"""The joint conventions of DESIGN.md: 13 public joints and the skeleton edges."""

from __future__ import annotations

JOINT_NAMES: tuple[str, ...] = (
    "head",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)
"""The 13 joints, in DESIGN.md order (COCO-17 minus eyes/ears, nose -> head)."""

N_JOINTS = len(JOINT_NAMES)
JOINT_INDEX: dict[str, int] = {name: i for i, name in enumerate(JOINT_NAMES)}

# Bones between the 13 joints (for drawing, bone-length constraints, Rerun).
BONES: tuple[tuple[int, int], ...] = tuple(
    (JOINT_INDEX[a], JOINT_INDEX[b])
    for a, b in (
        ("head", "left_shoulder"),
        ("head", "right_shoulder"),
        ("left_shoulder", "right_shoulder"),
        ("left_shoulder", "left_elbow"),
        ("left_elbow", "left_wrist"),
        ("right_shoulder", "right_elbow"),
        ("right_elbow", "right_wrist"),
        ("left_shoulder", "left_hip"),
        ("right_shoulder", "right_hip"),
        ("left_hip", "right_hip"),
        ("left_hip", "left_knee"),
        ("left_knee", "left_ankle"),
        ("right_hip", "right_knee"),
        ("right_knee", "right_ankle"),
    )
)

# Index permutation that swaps left and right (the mirror of a pose).
MIRROR: tuple[int, ...] = tuple(
    JOINT_INDEX[
        n.replace("left_", "tmp_").replace("right_", "left_").replace("tmp_", "right_")
    ]
    for n in JOINT_NAMES
)
