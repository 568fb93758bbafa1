"""Cameras placed by viewpoint (azimuth, elevation) around the walker (DESIGN.md).

``azimuth_deg`` is measured on the ground plane from the walking direction (+x)
counter-clockwise seen from above (0 = ahead, 90 = on the walker's left);
``elevation_deg`` is the angle above the horizontal plane through the target.
Image coordinates: pixels, origin top-left, u right, v down, pixel centres at
integer coordinates (OpenCV's convention).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Camera", "aimed_rotation", "viewpoint_direction", "world_to_camera_rotation"]


def viewpoint_direction(azimuth_deg: np.ndarray | float, elevation_deg: np.ndarray | float) -> np.ndarray:
    """Unit vector from the target towards the camera, shape (..., 3)."""
    a, e = np.deg2rad(azimuth_deg), np.deg2rad(elevation_deg)
    return np.stack(np.broadcast_arrays(np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)), axis=-1)


def world_to_camera_rotation(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """Rotation whose rows are the image u axis, the image v axis and the viewing direction.

    The camera looks at the target with no roll: u is horizontal, v points down
    the image. This is the ``R_c`` of the self-calibration output (DESIGN.md).
    """
    f = -viewpoint_direction(azimuth_deg, elevation_deg)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    return np.stack([r, np.cross(f, r), f])


def aimed_rotation(azimuth_deg: float, elevation_deg: float, offset_px: np.ndarray, focal_px: float) -> np.ndarray:
    """The rotation (rows u, v, viewing direction) of a camera without roll that sees the walker from
    (azimuth, elevation) at ``offset_px`` = (du, dv) from its principal point.

    :func:`world_to_camera_rotation` is the camera that looks straight at the
    walker; a real camera sees the walker off its axis by ``atan(du / f)`` and
    more, which the walker-relative viewpoint of Izo–Grimson does not know. With
    the camera's x axis horizontal and the walker's ray ``w`` (world, towards the
    walker; azimuth ``a``, elevation ``b``) seen at ``d`` = (du, dv, f) / |.|
    (camera), the axis's azimuth is ``a + asin(d_x / cos b)`` (``d_x`` is the
    ray's component along the horizontal x axis) and its elevation solves
    ``cos e cos b cos(az - a) + sin e sin b = d_z``; of the two roots the one
    whose v axis meets ``d_y`` is taken.
    """
    d = np.array([offset_px[0] / focal_px, offset_px[1] / focal_px, 1.0])
    d /= np.linalg.norm(d)
    w = -viewpoint_direction(azimuth_deg, elevation_deg)
    a, b = np.arctan2(w[1], w[0]), np.arcsin(np.clip(w[2], -1.0, 1.0))
    az = a + np.arcsin(np.clip(d[0] / max(np.cos(b), 1e-9), -1.0, 1.0))
    c, s = np.cos(b) * np.cos(az - a), np.sin(b)
    gamma, spread = np.arctan2(s, c), np.arccos(np.clip(d[2] / np.hypot(c, s), -1.0, 1.0))
    best, rot = np.inf, None
    for el in (gamma - spread, gamma + spread):
        f = np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        x = np.cross(f, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        candidate = np.stack([x, np.cross(f, x), f])
        miss = float(np.linalg.norm(candidate @ w - d))
        if miss < best:
            best, rot = miss, candidate
    return rot


@dataclass(frozen=True)
class Camera:
    """A pinhole (or orthographic) camera looking at ``target`` from a viewpoint.

    Parameters
    ----------
    azimuth_deg, elevation_deg : float
        Viewpoint (DESIGN.md convention). Elevation must lie in (-90, 90).
    distance : float
        Metres from the target to the camera centre.
    image_size : (int, int)
        (width, height) in pixels.
    focal_px : float
        Focal length in pixels; for an orthographic camera, pixels per metre.
    orthographic : bool
        Orthographic projection instead of perspective.
    target : (float, float, float)
        World point on the optical axis (the walker's centroid, usually).
    """

    azimuth_deg: float
    elevation_deg: float
    distance: float = 10.0
    image_size: tuple[int, int] = (640, 480)
    focal_px: float = 1400.0
    orthographic: bool = False
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        if not -90.0 < self.elevation_deg < 90.0:
            raise ValueError(f"elevation_deg must lie in (-90, 90), got {self.elevation_deg}")
        if self.distance <= 0 or self.focal_px <= 0:
            raise ValueError(f"distance and focal_px must be positive, got {self.distance}, {self.focal_px}")
        w, h = self.image_size
        if int(w) != w or int(h) != h or w < 1 or h < 1:
            raise ValueError(f"image_size must be two positive integers (width, height), got {self.image_size}")
        object.__setattr__(self, "azimuth_deg", float(self.azimuth_deg) % 360.0)
        object.__setattr__(self, "image_size", (int(w), int(h)))
        object.__setattr__(self, "target", tuple(float(t) for t in self.target))

    @property
    def rotation(self) -> np.ndarray:
        """World-to-camera rotation, rows (u axis, v axis, viewing direction)."""
        return world_to_camera_rotation(self.azimuth_deg, self.elevation_deg)

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world coordinates."""
        return np.asarray(self.target) + self.distance * viewpoint_direction(self.azimuth_deg, self.elevation_deg)

    @property
    def principal_point(self) -> tuple[float, float]:
        w, h = self.image_size
        return ((w - 1) / 2.0, (h - 1) / 2.0)

    def project(self, points: np.ndarray) -> np.ndarray:
        """Pixel coordinates of world points, shape (..., 3) -> (..., 2)."""
        p = (np.asarray(points, dtype=float) - self.position) @ self.rotation.T
        cx, cy = self.principal_point
        if self.orthographic:
            return np.stack([cx + self.focal_px * p[..., 0], cy + self.focal_px * p[..., 1]], axis=-1)
        if np.any(p[..., 2] <= 0):
            raise ValueError("a point lies behind the camera")
        return np.stack([cx + self.focal_px * p[..., 0] / p[..., 2], cy + self.focal_px * p[..., 1] / p[..., 2]], axis=-1)

    def camera_to_world(self) -> np.ndarray:
        """4x4 pose in OpenGL's convention (x right, y up, looking down -z)."""
        R = self.rotation
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2] = R[0], -R[1], -R[2]
        pose[:3, 3] = self.position
        return pose
