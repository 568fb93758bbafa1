"""Files the peers read: a Pose2Sim / anipose calibration TOML and an OpenSim TRC.

Both are written by hand (no TOML writer is installed; the layouts are small):

- calibration TOML, as Pose2Sim's ``calibration.toml_write`` writes it and
  aniposelib's ``CameraGroup.load`` reads it: one table per camera with
  ``name``, ``size`` [W, H], ``matrix`` (3x3 intrinsics), ``distortions``
  (k1, k2, p1, p2), ``rotation`` (Rodrigues vector, world to camera),
  ``translation`` (``x_cam = R X + t``, metres) and ``fisheye = false``, then a
  ``[metadata]`` table;
- TRC, as Pose2Sim's triangulation writes it for OpenSim: the header lines
  ``PathFileType 4 (X/Y/Z) <file>``, the ``DataRate ... OrigNumFrames`` names and
  values, ``Frame# Time <marker> ...`` and ``X1 Y1 Z1 ...``, then one
  tab-separated row per frame; metres, Y up (Pose2Sim's ``zup2yup``: the Z-up
  world's (x, y, z) is written as (y, z, x)); missing joints are empty cells.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from estimator.joints import JOINT_NAMES
from estimator.pinhole import PinholeCameras

__all__ = ["TRC_MARKERS", "write_calibration_toml", "write_trc"]

TRC_MARKERS: tuple[str, ...] = tuple(
    {"left": "L", "right": "R"}.get(name.partition("_")[0], "") + name.rpartition("_")[2].title()
    for name in JOINT_NAMES)
"""The 13 joints' marker names in the TRC, in :data:`estimator.joints.JOINT_NAMES` order, Pose2Sim's
spelling: ``Head``, ``LShoulder``, ``RShoulder``, ... ``RAnkle``."""


def _num(v: float) -> str:
    if not math.isfinite(v):
        raise ValueError(f"cannot write a non-finite number ({v}) to the calibration")
    return repr(float(v))


def _array(values) -> str:
    a = np.asarray(values)
    if a.ndim == 1:
        return "[ " + ", ".join(_num(v) for v in a) + "]"
    return "[ " + ", ".join(_array(r) for r in a) + "]"


def write_calibration_toml(path: Path, names: Sequence[str], sizes: np.ndarray, cameras: PinholeCameras, *,
                           metadata: dict[str, str | float | bool] | None = None) -> None:
    """Write cameras (world to camera, metres) as a Pose2Sim / anipose calibration TOML.

    Parameters
    ----------
    names : sequence of str
        Camera names: each is a table's key and its ``name``.
    sizes : ndarray of shape (C, 2)
        Image (width, height) per camera.
    metadata : dict, optional
        Extra ``[metadata]`` entries besides ``adjusted = false`` and ``error``.
    """
    rotvec = Rotation.from_matrix(cameras.rotations).as_rotvec()
    lines = []
    for c, name in enumerate(names):
        key = name if re.fullmatch(r"[A-Za-z0-9_-]+", name) else json.dumps(str(name))
        lines += [f"[{key}]", f"name = {json.dumps(str(name))}",
                  f"size = {_array(np.asarray(sizes[c], float))}", f"matrix = {_array(cameras.matrices[c])}",
                  f"distortions = {_array(np.zeros(4))}", f"rotation = {_array(rotvec[c])}",
                  f"translation = {_array(cameras.translations[c])}", "fisheye = false", ""]
    meta = {"adjusted": False, "error": 0.0, **(metadata or {})}
    lines.append("[metadata]")
    for key, value in meta.items():
        text = ("true" if value else "false") if isinstance(value, bool) else (
            _num(value) if isinstance(value, (int, float)) else json.dumps(str(value)))
        lines.append(f"{key} = {text}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")


def write_trc(path: Path, joints_zup: np.ndarray, fps: float, frames: Sequence[int] | None = None) -> None:
    """Write joints (T, 13, 3) of a Z-up world in metres as an OpenSim TRC (Y up).

    ``frames`` are the source frame numbers (``Frame#``; default 1..T); ``Time``
    is ``(frame - first frame) / fps``.
    """
    x = np.asarray(joints_zup, float)
    t = len(x)
    numbers = list(range(1, t + 1)) if frames is None else [int(f) for f in frames]
    if len(numbers) != t or fps <= 0:
        raise ValueError(f"need one frame number per frame and fps > 0, got {len(numbers)} for {t}, fps {fps}")
    yup = x[..., [1, 2, 0]]
    header = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        "\t".join(map(str, [fps, fps, t, len(TRC_MARKERS), "m", fps, numbers[0], t])),
        "Frame#\tTime\t" + "\t\t\t".join(TRC_MARKERS) + "\t\t",
        "\t\t" + "\t".join(f"X{i + 1}\tY{i + 1}\tZ{i + 1}" for i in range(len(TRC_MARKERS))),
    ]
    rows = []
    for k in range(t):
        cells = [str(numbers[k]), f"{(numbers[k] - numbers[0]) / fps:.6f}"]
        cells += ["" if not np.isfinite(v) else f"{v:.6f}" for v in yup[k].ravel()]
        rows.append("\t".join(cells))
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(header + rows) + "\n")
