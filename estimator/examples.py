"""Rendered examples of the walking body: the raw material of the appearance model (§4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .joints import N_JOINTS

__all__ = ["Examples"]


@dataclass(frozen=True)
class Examples:
    """A set of rendered examples (Izo–Grimson §4: the quadruples (s, psi, theta, phi)).

    Attributes
    ----------
    silhouettes : ndarray of shape (N, H, W), uint8
        Binary silhouettes (0/255), each a crop around the body.
    joints2d : ndarray of shape (N, 13, 2)
        The 13 joints projected into each silhouette's pixel coordinates (u right,
        v down), same crop as ``silhouettes``.
    phase : ndarray of shape (N,)
        Walking phase in [0, 1) (DESIGN.md).
    azimuth_deg, elevation_deg : ndarray of shape (N,)
        Camera viewpoint of each example (DESIGN.md convention).
    style : ndarray of shape (N,), int
        Index of the body size/style the example was rendered with (0 when one body).
    """

    silhouettes: np.ndarray
    joints2d: np.ndarray
    phase: np.ndarray
    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    style: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.phase)
        if self.silhouettes.ndim != 3 or len(self.silhouettes) != n:
            raise ValueError(f"silhouettes must have shape ({n}, H, W), got {self.silhouettes.shape}")
        if self.joints2d.shape != (n, N_JOINTS, 2):
            raise ValueError(f"joints2d must have shape ({n}, {N_JOINTS}, 2), got {self.joints2d.shape}")
        for name in ("azimuth_deg", "elevation_deg", "style"):
            if getattr(self, name).shape != (n,):
                raise ValueError(f"{name} must have shape ({n},), got {getattr(self, name).shape}")

    def __len__(self) -> int:
        return len(self.phase)
