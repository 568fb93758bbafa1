"""Binary-mask operations the segmenter shares: filling enclosed holes, keeping large components."""

from __future__ import annotations

import cv2
import numpy as np

__all__ = ["filled", "large_components"]


def large_components(mask: np.ndarray, min_area: float, *, connectivity: int = 8,
                     of_largest: bool = False) -> np.ndarray:
    """``mask`` (0/255 uint8) with only its components of at least ``min_area`` pixels, or, with
    ``of_largest``, of at least ``min_area`` times the largest component's area."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=connectivity)
    areas = stats[:, cv2.CC_STAT_AREA]
    floor = min_area * (areas[1:].max() if of_largest and n > 1 else 1)
    keep = areas >= floor
    keep[0] = False  # the background label
    return np.where(keep[labels], 255, 0).astype(np.uint8)


def filled(mask: np.ndarray, min_fraction: float = 0.0) -> np.ndarray:
    """``mask`` (0/255 uint8) with the holes it encloses filled (what a flood fill from outside, a
    one-pixel frame added around it, does not reach), each hole that is at least ``min_fraction`` of
    the mask's area with its holes."""
    outside = cv2.copyMakeBorder(mask, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0)
    cv2.floodFill(outside, None, (0, 0), 255)
    holes = cv2.bitwise_not(outside[1:-1, 1:-1])
    if min_fraction > 0:
        holes = large_components(holes, min_fraction * (cv2.countNonZero(mask) + cv2.countNonZero(holes)),
                                 connectivity=4)
    return cv2.bitwise_or(mask, holes)
