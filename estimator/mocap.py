"""Readers for recorded motion (ASF/AMC and BVH) and the person frame.

Both readers return a :class:`Motion`: the positions of the posecal skeleton's
joints (:data:`estimator.skeleton.FULL_JOINT_NAMES`) per frame, in metres, in a
Z-up world. :meth:`Motion.person_frame` then puts each frame in the person frame
of DESIGN.md (origin at the centroid of the 13 joints, x = walking direction,
y = the walker's left, z = up), which is what the gait fit and the synthetic
sequences use.

Notes
-----
ASF/AMC follows the Acclaim format as used by the CMU database: a bone's local
rotation is ``C @ M @ C^-1`` with ``C`` from its ``axis`` line and ``M`` from the
AMC degrees of freedom, composed down the hierarchy; lengths are in units of
``1 / :units length`` inches. BVH applies ``CHANNELS`` rotations in the order
written, per joint.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.spatial.transform import Rotation

from .joints import N_JOINTS
from .skeleton import FULL_JOINT_NAMES

__all__ = ["Motion", "bvh_positions", "read_asf_amc", "read_bvh", "read_motion"]

_INCH = 0.0254
# Y-up recording frame -> Z-up posecal world (a proper rotation: +90 deg about x).
_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])

# posecal joint -> recorded points averaged to make it. A recorded point is named
# after the bone that starts there (BVH's JOINT names, CMU bone names), or
# "<bone>_end" for the end of a leaf bone.
_CMU_POINTS: dict[str, tuple[str, ...]] = {
    "head": ("head", "head_end"),
    "left_shoulder": ("lhumerus",),
    "right_shoulder": ("rhumerus",),
    "left_elbow": ("lradius",),
    "right_elbow": ("rradius",),
    "left_wrist": ("lwrist",),
    "right_wrist": ("rwrist",),
    "left_hip": ("lfemur",),
    "right_hip": ("rfemur",),
    "left_knee": ("ltibia",),
    "right_knee": ("rtibia",),
    "left_ankle": ("lfoot",),
    "right_ankle": ("rfoot",),
    "pelvis": ("root",),
    "spine": ("thorax",),
    "neck": ("lowerneck",),
    "left_hand": ("lhand",),
    "right_hand": ("rhand",),
    "left_toe": ("ltoes",),
    "right_toe": ("rtoes",),
}

# Common BVH naming (CMU conversions by Bruce Hahne, Mixamo-like rigs).
_BVH_ALIASES: dict[str, str] = {
    "hips": "root",
    "spine1": "thorax",
    "neck": "lowerneck",
    "neck1": "upperneck",
    "leftarm": "lhumerus",
    "leftforearm": "lradius",
    "lefthand": "lwrist",
    "leftfingerbase": "lhand",
    "rightarm": "rhumerus",
    "rightforearm": "rradius",
    "righthand": "rwrist",
    "rightfingerbase": "rhand",
    "leftupleg": "lfemur",
    "leftleg": "ltibia",
    "leftfoot": "lfoot",
    "lefttoebase": "ltoes",
    "rightupleg": "rfemur",
    "rightleg": "rtibia",
    "rightfoot": "rfoot",
    "righttoebase": "rtoes",
}


@dataclass(frozen=True)
class Motion:
    """Recorded or synthesised motion of the posecal skeleton.

    Attributes
    ----------
    positions : ndarray of shape (T, J, 3)
        Joint positions in metres, Z up, J = ``len(FULL_JOINT_NAMES)``; the first
        13 are the public joints of DESIGN.md.
    fps : float
        Frames per second.
    source : str
        Where the motion came from (file name), for reports.
    """

    positions: np.ndarray
    fps: float
    source: str = ""

    def __post_init__(self) -> None:
        p = np.asarray(self.positions, dtype=float)
        if p.ndim != 3 or p.shape[1:] != (len(FULL_JOINT_NAMES), 3):
            raise ValueError(
                f"positions must have shape (T, {len(FULL_JOINT_NAMES)}, 3), got {p.shape}"
            )
        if self.fps <= 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        object.__setattr__(self, "positions", p)

    def __len__(self) -> int:
        return self.positions.shape[0]

    @property
    def joints(self) -> np.ndarray:
        """The 13 public joints, shape (T, 13, 3), in the recording's world."""
        return self.positions[:, :N_JOINTS]

    def heading(self, *, window_s: float = 1.0) -> np.ndarray:
        """Walking direction per frame, radians from the world x axis, shape (T,).

        The pelvis's ground-plane velocity averaged over ``window_s`` seconds
        (about one gait cycle, so sway cancels). Frames where the walker barely
        moves take the overall direction of travel.
        """
        pelvis = self.positions[:, FULL_JOINT_NAMES.index("pelvis"), :2]
        size = max(1, int(round(window_s * self.fps)))
        velocity = np.gradient(uniform_filter1d(pelvis, size, axis=0, mode="nearest"), axis=0)
        overall = pelvis[-1] - pelvis[0]
        slow = np.linalg.norm(velocity, axis=1) * self.fps < 0.1
        velocity[slow] = overall
        return np.arctan2(velocity[:, 1], velocity[:, 0])

    def heading_frame(self, *, window_s: float = 1.0) -> np.ndarray:
        """Positions in the walker's heading frame, shape (T, J, 3).

        Each frame is rotated about z so the walking direction is +x, and shifted
        so the pelvis's path, averaged over ``window_s`` (about a gait cycle),
        passes through x = y = 0; z is unchanged (the recording's floor).
        """
        h = self.heading(window_s=window_s)
        pelvis = self.positions[:, FULL_JOINT_NAMES.index("pelvis"), :2]
        size = max(1, int(round(window_s * self.fps)))
        path = uniform_filter1d(pelvis, size, axis=0, mode="nearest")
        c, s = np.cos(h)[:, None], np.sin(h)[:, None]
        x = self.positions[..., 0] - path[:, None, 0]
        y = self.positions[..., 1] - path[:, None, 1]
        return np.stack([c * x + s * y, -s * x + c * y, self.positions[..., 2]], axis=-1)

    def person_frame(self, *, window_s: float = 1.0) -> np.ndarray:
        """Positions in the person frame of DESIGN.md, shape (T, J, 3).

        The heading frame shifted so the centroid of the 13 public joints is the
        origin of each frame.
        """
        p = self.heading_frame(window_s=window_s)
        return p - p[:, :N_JOINTS].mean(axis=1, keepdims=True)


def _rot(order: str, angles_deg: np.ndarray) -> np.ndarray:
    """Rotation matrices ``R_a1 @ R_a2 @ R_a3`` for axes ``order`` = "a1a2a3", (..., 3, 3).

    That is scipy's intrinsic (upper-case) sequence: the BVH channel order, and
    Acclaim's ``axis ... XYZ`` read as ``R_x R_y R_z`` applied to column vectors
    from the right, i.e. ``R_z`` first.
    """
    return Rotation.from_euler(order.upper(), angles_deg, degrees=True).as_matrix()


def _acclaim_rot(angles_deg: np.ndarray) -> np.ndarray:
    """Acclaim ``axis XYZ`` / ``rx ry rz`` rotations: ``R_z @ R_y @ R_x`` (fixed axes)."""
    return Rotation.from_euler("xyz", angles_deg, degrees=True).as_matrix()


def _to_motion(points: dict[str, np.ndarray], fps: float, unit: float, source: str) -> Motion:
    """Collect posecal joints from named recorded points (Y-up, recording units)."""
    missing = sorted({p for pts in _CMU_POINTS.values() for p in pts} - points.keys())
    if missing:
        raise ValueError(f"{source}: skeleton lacks the points {missing}")
    joints = np.stack(
        [np.mean([points[p] for p in _CMU_POINTS[name]], axis=0) for name in FULL_JOINT_NAMES],
        axis=1,
    )
    return Motion(positions=joints @ _Y_UP_TO_Z_UP.T * unit, fps=fps, source=source)


# --------------------------------------------------------------------------- ASF/AMC


@dataclass(frozen=True)
class _Bone:
    name: str
    direction: np.ndarray
    length: float
    axis: np.ndarray  # C, from the ``axis`` line
    dofs: tuple[str, ...]


def _parse_asf(text: str) -> tuple[float, dict[str, _Bone], dict[str, list[str]]]:
    length_unit = 1.0
    bones: dict[str, _Bone] = {}
    children: dict[str, list[str]] = {}
    section = None
    current: dict[str, object] = {}
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        if line.startswith(":"):
            section = line.split()[0]
            continue
        words = line.split()
        if section == ":units" and words[0] == "length":
            length_unit = float(words[1])
        elif section == ":bonedata":
            if words[0] == "begin":
                current = {"dofs": ()}
            elif words[0] == "end":
                axis = np.array(current["axis"][:3], float)
                bones[current["name"]] = _Bone(
                    name=current["name"],
                    direction=np.array(current["direction"], float),
                    length=float(current["length"]),
                    axis=_acclaim_rot(axis),
                    dofs=tuple(current["dofs"]),
                )
            elif words[0] in ("name",):
                current["name"] = words[1]
            elif words[0] == "direction":
                current["direction"] = [float(w) for w in words[1:4]]
            elif words[0] == "length":
                current["length"] = words[1]
            elif words[0] == "axis":
                current["axis"] = [float(w) for w in words[1:4]] + [words[4]]
            elif words[0] == "dof":
                current["dofs"] = tuple(w.lower() for w in words[1:])
        elif section == ":hierarchy" and words[0] not in ("begin", "end"):
            children.setdefault(words[0], []).extend(words[1:])
    return length_unit, bones, children


def read_asf_amc(asf_path: str | os.PathLike, amc_path: str | os.PathLike, *, fps: float = 120.0) -> Motion:
    """Read an Acclaim skeleton and motion (CMU mocap) into a :class:`Motion`.

    Parameters
    ----------
    asf_path, amc_path : path
        The skeleton (.asf) and the motion (.amc).
    fps : float, optional
        Frame rate of the AMC file (not stored in it; CMU uses 120 Hz).
    """
    with open(asf_path) as fh:
        length_unit, bones, children = _parse_asf(fh.read())
    frames: list[dict[str, list[float]]] = []
    with open(amc_path) as fh:
        for raw in fh:
            line = raw.strip()
            if not line or line[0] in "#:":
                continue
            words = line.split()
            if words[0].isdigit() and len(words) == 1:
                frames.append({})
            elif frames:
                frames[-1][words[0]] = [float(w) for w in words[1:]]
    if not frames:
        raise ValueError(f"{amc_path}: no frames")
    n = len(frames)
    root = np.array([f["root"] for f in frames])  # TX TY TZ RX RY RZ
    rot_root = _acclaim_rot(root[:, 3:6])
    points: dict[str, np.ndarray] = {"root": root[:, :3]}
    global_rot: dict[str, np.ndarray] = {"root": rot_root}
    end: dict[str, np.ndarray] = {"root": root[:, :3]}
    order = ["root"]
    for parent in order:  # breadth-first over the hierarchy
        for name in children.get(parent, []):
            order.append(name)
            bone = bones[name]
            angles = np.zeros((n, 3))
            values = np.array([f.get(name, [0.0] * len(bone.dofs)) for f in frames]).reshape(n, -1)
            for k, dof in enumerate(bone.dofs):
                if dof in ("rx", "ry", "rz"):
                    angles[:, "xyz".index(dof[1])] = values[:, k]
            local = bone.axis @ _acclaim_rot(angles) @ bone.axis.T
            global_rot[name] = global_rot[parent] @ local
            points[name] = end[parent]
            # Acclaim: the bone direction is given in the global frame at rest.
            end[name] = end[parent] + global_rot[name] @ (bone.direction * bone.length)
            if not children.get(name):
                points[f"{name}_end"] = end[name]
    unit = _INCH / length_unit
    return _to_motion(points, fps, unit, os.path.basename(str(amc_path)))


# --------------------------------------------------------------------------- BVH


def read_bvh(path: str | os.PathLike, *, unit: float | None = None) -> Motion:
    """Read a BVH file into a :class:`Motion`.

    Parameters
    ----------
    path : path
        The .bvh file. Joint names may be CMU bone names or common BVH names
        (``Hips``, ``LeftUpLeg``, ...).
    unit : float, optional
        Metres per file unit. By default it is chosen among metres, centimetres,
        inches and CMU's 1/0.45 inch so that the skeleton's height is plausible.
    """
    joints, ends, frame_time = bvh_positions(path)
    points: dict[str, np.ndarray] = {}
    for name, pos in joints.items():
        points.setdefault(_BVH_ALIASES.get(name.lower(), name.lower()), pos)
    for name, pos in ends.items():
        points.setdefault(f"{_BVH_ALIASES.get(name.lower(), name.lower())}_end", pos)
    if "head_end" not in points and "head" in points:
        points["head_end"] = points["head"]
    if unit is None:
        height = np.ptp(np.stack(list(points.values()), axis=1)[0] @ _Y_UP_TO_Z_UP.T, axis=0)[2]
        candidates = np.array([1.0, 0.01, _INCH, _INCH / 0.45])
        unit = float(candidates[np.argmin(np.abs(np.log(height * candidates / 1.7)))])
    return _to_motion(points, 1.0 / frame_time, unit, os.path.basename(str(path)))


def bvh_positions(path: str | os.PathLike) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """Forward kinematics of a BVH file: each joint's position (T, 3) by its name in the file, each End
    Site's by its joint's name, in the file's units and axes; and the frame time in seconds."""
    with open(path) as fh:
        tokens = fh.read().split()
    pos = 0
    names: list[str] = []
    parents: list[int] = []
    offsets: list[np.ndarray] = []
    channels: list[list[str]] = []
    stack: list[int] = []
    end_sites: list[tuple[int, np.ndarray]] = []
    if tokens[0] != "HIERARCHY":
        raise ValueError(f"{path}: not a BVH file")
    pos = 1
    while tokens[pos] != "MOTION":
        tok = tokens[pos]
        if tok in ("ROOT", "JOINT"):
            names.append(tokens[pos + 1])
            parents.append(stack[-1] if stack else -1)
            pos += 2
        elif tok == "End":
            # End Site { OFFSET x y z }
            end_sites.append((stack[-1], np.array(tokens[pos + 4 : pos + 7], float)))
            pos += 8
        elif tok == "{":
            stack.append(len(names) - 1)
            pos += 1
        elif tok == "}":
            stack.pop()
            pos += 1
        elif tok == "OFFSET":
            offsets.append(np.array(tokens[pos + 1 : pos + 4], float))
            pos += 4
        elif tok == "CHANNELS":
            count = int(tokens[pos + 1])
            channels.append(tokens[pos + 2 : pos + 2 + count])
            pos += 2 + count
        else:
            raise ValueError(f"{path}: unexpected token {tok!r}")
    n_frames = int(tokens[pos + 2])
    frame_time = float(tokens[pos + 5])
    data = np.array(tokens[pos + 6 :], float)
    n_channels = sum(len(c) for c in channels)
    if data.size != n_frames * n_channels:
        raise ValueError(f"{path}: expected {n_frames} x {n_channels} values, got {data.size}")
    data = data.reshape(n_frames, n_channels)

    glob_rot: list[np.ndarray] = []
    glob_pos: list[np.ndarray] = []
    col = 0
    for j, chans in enumerate(channels):
        translation = np.broadcast_to(offsets[j], (n_frames, 3)).copy()
        rot_axes, rot_cols = "", []
        for c in chans:
            axis = "XYZ".index(c[0].upper())
            if c.lower().endswith("position"):
                translation[:, axis] = data[:, col]
            else:
                rot_axes += c[0].upper()
                rot_cols.append(col)
            col += 1
        # BVH applies the channels in the written order, about moving axes.
        local = _rot(rot_axes, data[:, rot_cols]) if rot_axes else np.eye(3)
        p = parents[j]
        if p < 0:
            glob_rot.append(np.broadcast_to(local, (n_frames, 3, 3)))
            glob_pos.append(translation)
        else:
            glob_pos.append(glob_pos[p] + np.einsum("tij,tj->ti", glob_rot[p], translation))
            glob_rot.append(glob_rot[p] @ local)

    joints: dict[str, np.ndarray] = {}
    for j, name in enumerate(names):
        joints.setdefault(name, glob_pos[j])
    ends: dict[str, np.ndarray] = {}
    for j, offset in end_sites:
        ends.setdefault(names[j], glob_pos[j] + np.einsum("tij,j->ti", glob_rot[j], offset))
    return joints, ends, frame_time


def read_motion(path: str | os.PathLike, *, fps: float = 120.0) -> Motion:
    """Read ``.bvh`` or ``.amc`` (its ``.asf`` found beside it: ``16_15.amc`` -> ``16.asf``)."""
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    if ext == ".bvh":
        return read_bvh(path)
    if ext == ".amc":
        folder, base = os.path.split(path)
        stem = os.path.splitext(base)[0]
        candidates = [os.path.join(folder, stem + ".asf"), os.path.join(folder, stem.split("_")[0] + ".asf")]
        for asf in candidates:
            if os.path.exists(asf):
                return read_asf_amc(asf, path, fps=fps)
        raise FileNotFoundError(f"no skeleton for {path}: looked for {', '.join(candidates)}")
    raise ValueError(f"unknown motion format {ext!r}: expected .bvh or .amc")
