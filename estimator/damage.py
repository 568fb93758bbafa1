"""Damage that real segmenters leave on silhouettes, drawn reproducibly.

posecal's own renders are clean; a background subtractor on a real camera is
not. These models put the typical faults onto full-frame binary silhouettes
so that estimation and feedback can be measured on inputs the generator did
not make (docs/ROBUSTNESS.md):

- ``salt``: isolated foreground pixels over the whole frame (sensor noise,
  compression, leaves);
- ``blobs``: a few small compact regions away from the walker (a bag, a
  door, a reflection);
- ``holes``: discs cut out of the body (clothing that matches the background);
- ``cut_limb``: a forearm or shin missing from elbow/knee down to the end
  (the same, on a limb), which can split the silhouette;
- ``shadow``: a dark ground-plane projection of the body attached at the
  feet (the walker's own shadow or floor reflection classified as foreground);
- ``side_shadow``: the shadow of a low light beside and in front of the walker,
  cast away from the camera: it rises from the feet to one side, beside the
  legs, rather than below them;
- ``second_person``: another walker of similar size elsewhere in the frame;
- ``low_wall``: the lowest 15-40 % of the walker hidden behind something in
  front of them (a low wall, a bench, a parked car);
- ``fixed_wall``: the same wall fixed in the image, as a real one is: every
  row below one row of the camera's frame hidden, so the share hidden changes
  as the walker nears or recedes (15-40 % at the camera's median walker box);
- ``wall_end``: a fixed wall that ends in the image: the rows below one row
  hidden on one side of one column only, where the walker crosses it midway
  (30-70 % into the window), so they are behind it for part of the window
  and whole for the rest (a bench, a parked car, the end of a wall);
- ``all``: every one of the above on the same frames but ``side_shadow`` (one
  light casts one shadow) and the walls (a wall would hide the shadow at the feet).

Each function takes one silhouette (uint8 0/255, full frame) and a
``numpy.random.Generator`` and returns a new array; :func:`damage_sequence`
applies a kind to every frame of every camera with one seed.
:func:`detector_keypoints` does the same for 2D joints: a pose detector's
kinds of error on exact joints.
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from .joints import JOINT_NAMES

__all__ = ["DAMAGE_KINDS", "damage", "damage_sequence", "detector_keypoints", "parse_damage", "salt", "blobs", "holes",
           "cut_limb", "shadow", "side_shadow", "low_wall", "fixed_wall", "second_person"]

_J = {name: i for i, name in enumerate(JOINT_NAMES)}
# (upper joint, end joint) of the limbs a cut can remove: forearms and shins.
_LIMBS = [("left_elbow", "left_wrist"), ("right_elbow", "right_wrist"),
          ("left_knee", "left_ankle"), ("right_knee", "right_ankle")]


def _box(sil: np.ndarray) -> tuple[int, int, int, int] | None:
    x, y, w, h = cv2.boundingRect(sil)
    return None if w == 0 or h == 0 else (x, y, w, h)


def salt(sil: np.ndarray, rng: np.random.Generator, *, fraction: float = 0.002) -> np.ndarray:
    """Set ``fraction`` of the frame's pixels, at random, to foreground."""
    out = sil.copy()
    n = int(round(fraction * out.size))
    idx = rng.choice(out.size, size=n, replace=False)
    out.reshape(-1)[idx] = 255
    return out


def blobs(sil: np.ndarray, rng: np.random.Generator, *, n: int = 2, size: float = 0.06,
          box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Add ``n`` filled ellipses of about ``size`` of the walker's height, at least half its
    height from the walker's box (``box``, default: the silhouette's); a blob for which 20
    random centres find no such place is not drawn."""
    out = sil.copy()
    box = _box(sil) if box is None else box
    H, W = sil.shape
    h = box[3] if box else H // 4
    r = max(2, int(round(size * h)))
    for _ in range(n):
        for _try in range(20):  # a centre at least half a walker-height from the walker's box
            cx, cy = int(rng.integers(r, W - r)), int(rng.integers(r, H - r))
            if box is None:
                break
            x, y, w, bh = box
            dx = max(x - cx, 0, cx - (x + w))
            dy = max(y - cy, 0, cy - (y + bh))
            if max(dx, dy) > 0.5 * h:
                break
        else:
            continue  # nowhere away from the walker
        axes = (r, max(2, int(round(r * rng.uniform(0.5, 1.5)))))
        cv2.ellipse(out, (cx, cy), axes, float(rng.uniform(0, 180)), 0, 360, 255, -1)
    return out


def holes(sil: np.ndarray, rng: np.random.Generator, *, n: int = 3, size: float = 0.05,
          box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Cut ``n`` discs of radius ``size`` of the walker's height (``box``, default: the
    silhouette's) out of the foreground."""
    out = sil.copy()
    ys, xs = np.nonzero(sil)
    if ys.size == 0:
        return out
    h = box[3] if box is not None else ys.max() - ys.min() + 1
    r = max(1, int(round(size * h)))
    for k in rng.choice(ys.size, size=n):
        cv2.circle(out, (int(xs[k]), int(ys[k])), r, 0, -1)
    return out


def cut_limb(sil: np.ndarray, rng: np.random.Generator, joints2d: np.ndarray | None = None, *,
             width: float = 0.09, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """Erase one forearm or shin (a thick line, ``width`` of the walker's height, from
    elbow/knee to wrist/ankle and beyond).

    Needs the frame's 13 ``joints2d`` (the truth); without them the lower
    quarter of one side of the walker's box (``box``, default: the
    silhouette's) is erased instead.
    """
    out = sil.copy()
    box = _box(sil) if box is None else box
    if box is None:
        return out
    x, y, w, h = box
    thick = max(2, int(round(width * h)))
    if joints2d is None or not np.all(np.isfinite(joints2d)):
        side = int(rng.integers(2))
        out[y + 3 * h // 4:y + h, x + side * w // 2:x + (side + 1) * w // 2] = 0
        return out
    a, b = _LIMBS[int(rng.integers(len(_LIMBS)))]
    p, q = np.asarray(joints2d[_J[a]], float), np.asarray(joints2d[_J[b]], float)
    end = q + 0.25 * (q - p)  # the hand or foot too
    start = p + 0.15 * (q - p)  # from just below the elbow or knee
    cv2.line(out, tuple(int(round(v)) for v in start), tuple(int(round(v)) for v in end), 0, thick)
    return out


def shadow(sil: np.ndarray, rng: np.random.Generator, *, length: tuple[float, float] = (0.25, 0.6),
           slant: tuple[float, float] = (-1.2, 1.2)) -> np.ndarray:
    """Attach the body's shadow on the ground: the silhouette mirrored about its feet,
    squashed to ``length`` of its height and sheared sideways by ``slant`` (ratio of
    sideways to downward displacement), as a light behind the walker casts it towards
    the camera (or as a shiny floor reflects the walker)."""
    box = _box(sil)
    if box is None:
        return sil.copy()
    x, y, w, h = box
    k = float(rng.uniform(*length))
    s = float(rng.uniform(*slant))
    foot = y + h  # the ground line
    # v' = foot + k (foot - v); u' = u + s * (v' - foot): mirrored, squashed, sheared.
    m = np.array([[1.0, -s * k, s * k * foot], [0.0, -k, foot * (1 + k)]], np.float32)
    cast = cv2.warpAffine(sil, m, (sil.shape[1], sil.shape[0]), flags=cv2.INTER_NEAREST)
    return cv2.bitwise_or(sil, cast)


def side_shadow(sil: np.ndarray, rng: np.random.Generator, *, rise: tuple[float, float] = (0.05, 0.35),
                reach: tuple[float, float] = (0.4, 1.0)) -> np.ndarray:
    """Attach the shadow of a low light beside the walker, cast away from the camera: the
    silhouette squashed upwards from its feet to ``rise`` of its height (not mirrored: the
    head's shadow lies farthest, so highest in the image) and sheared to one side so that its
    far end lies ``reach`` heights beside the feet. At a small rise it is a band along the
    ground line (a light at the walker's side); it is never below the feet, so a cut below
    them cannot remove it."""
    box = _box(sil)
    if box is None:
        return sil.copy()
    x, y, w, h = box
    k = float(rng.uniform(*rise))
    s = float(rng.uniform(*reach)) / k * (1.0 if rng.random() < 0.5 else -1.0)
    foot = y + h
    # v' = foot - k (foot - v); u' = u + s (foot - v'): squashed upwards, sheared sideways.
    m = np.array([[1.0, -s * k, s * k * foot], [0.0, k, foot * (1 - k)]], np.float32)
    cast = cv2.warpAffine(sil, m, (sil.shape[1], sil.shape[0]), flags=cv2.INTER_NEAREST)
    return cv2.bitwise_or(sil, cast)


def low_wall(sil: np.ndarray, rng: np.random.Generator, *, hidden: tuple[float, float] = (0.15, 0.4)) -> np.ndarray:
    """Hide the lowest ``hidden`` of the walker's height (a low wall, a bench or a parked car
    between the walker and the camera): the silhouette ends in a straight cut above the feet."""
    box = _box(sil)
    if box is None:
        return sil.copy()
    x, y, w, h = box
    out = sil.copy()
    out[int(round(y + h * (1.0 - rng.uniform(*hidden)))):] = 0
    return out


def fixed_wall(sil: np.ndarray, rng: np.random.Generator, *, row: int | None = None,
               hidden: tuple[float, float] = (0.15, 0.4), end: tuple[int, bool] | None = None) -> np.ndarray:
    """Hide every row of the frame from ``row`` down (a wall's top edge, fixed in the image);
    without a ``row``, :func:`low_wall` on this frame (:func:`damage_sequence` gives each camera one).
    With ``end`` ``(column, left)`` the wall ends at that column: only the columns left of it (or
    right of it, ``left`` false) are hidden (``wall_end``)."""
    if row is None:
        return low_wall(sil, rng, hidden=hidden)
    out = sil.copy()
    cols = slice(None) if end is None else slice(None, max(0, end[0])) if end[1] else slice(max(0, end[0]), None)
    out[max(0, int(row)):, cols] = 0
    return out


def _wall_row(frames: list[np.ndarray | None], rng: np.random.Generator,
              hidden: tuple[float, float] = (0.15, 0.4)) -> int | None:
    """The row of a camera's fixed wall: ``hidden`` (drawn) of its median walker box above that box's bottom."""
    boxes = np.array([b for b in (_box(s) for s in frames if s is not None) if b is not None], float)
    if not len(boxes):
        return None
    bottom, height = np.median(boxes[:, 1] + boxes[:, 3]), np.median(boxes[:, 3])
    return int(round(bottom - float(rng.uniform(*hidden)) * height))


def _wall_end(frames: list[np.ndarray | None], rng: np.random.Generator,
              crossed: tuple[float, float] = (0.3, 0.7)) -> tuple[int, bool] | None:
    """Where a camera's wall ends, ``(column, left)``: at the walker's box centre in a frame drawn
    ``crossed`` into the frames with a walker, the wall on the side the walker comes from or goes to."""
    boxes = [b for b in (_box(s) for s in frames if s is not None) if b is not None]
    if not boxes:
        return None
    x, _, w, _ = boxes[min(len(boxes) - 1, int(rng.uniform(*crossed) * len(boxes)))]
    return int(round(x + w / 2)), bool(rng.random() < 0.5)


def second_person(sil: np.ndarray, rng: np.random.Generator, *, scale: tuple[float, float] = (0.6, 0.9)) -> np.ndarray:
    """Add another walker: the silhouette mirrored, rescaled (a bystander a little
    farther away) and moved at least one body width aside (clipped by the frame if
    it does not fit)."""
    box = _box(sil)
    if box is None:
        return sil.copy()
    x, y, w, h = box
    H, W = sil.shape
    f = float(rng.uniform(*scale))
    crop = cv2.flip(sil[y:y + h, x:x + w], 1)
    crop = cv2.resize(crop, (max(1, round(w * f)), max(1, round(h * f))), interpolation=cv2.INTER_NEAREST)
    ch, cw = crop.shape
    gap = int(rng.uniform(1.0, 3.0) * max(w, h // 3))
    left = x - gap - cw
    right = x + w + gap
    nx = left if (left >= 0 and (rng.random() < 0.5 or right + cw > W)) else right
    ny = int(np.clip(y + h - ch + rng.integers(-h // 10, h // 10 + 1), 0, max(0, H - ch)))
    out = sil.copy()
    x0, x1 = max(0, nx), min(W, nx + cw)
    if x1 > x0:
        out[ny:ny + ch, x0:x1] |= crop[:, x0 - nx:x1 - nx]
    return out


# In the order they are applied together: the walker's own faults first (shadow, holes,
# a cut limb), then what lies around it (a second person, blobs, salt).
_KINDS: dict[str, Callable] = {
    "shadow": shadow,
    "side_shadow": side_shadow,
    "low_wall": low_wall,
    "fixed_wall": fixed_wall,
    "wall_end": fixed_wall,  # with the end damage_sequence draws
    "holes": holes,
    "cut_limb": cut_limb,
    "second_person": second_person,
    "blobs": blobs,
    "salt": salt,
}
DAMAGE_KINDS: tuple[str, ...] = (*_KINDS, "all")
"""Damage kinds :func:`damage` knows, ``"all"`` applying every other one in turn but ``side_shadow``
(one light casts one shadow: ``all`` has the one at the feet) and the walls (a wall in front would
hide the shadow at the feet with them; docs/ROBUSTNESS.md, "A walker hidden below")."""
_WALLS = ("low_wall", "fixed_wall", "wall_end")
_ALL = tuple(k for k in _KINDS if k != "side_shadow" and k not in _WALLS)


_STEADY = ("shadow", "side_shadow", *_WALLS, "second_person")  # one draw per camera
_SCALED = ("holes", "blobs")  # sized by the walker's box (and cut_limb, which also takes the joints)


def parse_damage(kind: str) -> tuple[str, ...]:
    """The kinds named by ``kind`` ("all", one kind, or kinds joined by "+"), in the order applied."""
    names = _ALL if kind == "all" else tuple(kind.split("+"))
    bad = [k for k in names if k not in _KINDS]
    if bad or not names:
        raise ValueError(f"unknown damage {kind!r}; expected one of {', '.join(DAMAGE_KINDS)} "
                         "or kinds joined by '+'")
    return tuple(k for k in _KINDS if k in names)


def damage(sil: np.ndarray, kind: str, rng: np.random.Generator, joints2d: np.ndarray | None = None, *,
           steady_rng: np.random.Generator | None = None, wall_row: int | None = None,
           wall_end_at: tuple[int, bool] | None = None) -> np.ndarray:
    """Apply damage ``kind`` (one of :data:`DAMAGE_KINDS`, or kinds joined by ``+``) to one
    full-frame silhouette.

    ``joints2d`` (13, 2), the frame's true joints, is used by ``cut_limb``;
    ``steady_rng`` (default ``rng``) draws the shadow and the second person;
    ``wall_row`` is ``fixed_wall``'s and ``wall_end``'s row, ``wall_end_at`` where the latter ends.
    Holes, the cut and blobs are sized (and blobs kept away) by the walker's
    box in ``sil``, not by the silhouette as damaged so far (a shadow or a
    bystander would make them larger and push blobs onto the walker).
    Order for ``"all"``: the walker's own faults first (shadow, holes, a cut
    limb), then what lies around it (a second person, blobs, salt).
    """
    kinds = parse_damage(kind)
    walker = _box(sil)  # sizes and distances are the walker's, not those of the damage drawn before
    out = sil
    for k in kinds:
        r = steady_rng if (k in _STEADY and steady_rng is not None) else rng
        if k == "cut_limb":
            out = cut_limb(out, r, joints2d, box=walker)
        elif k in _SCALED:
            out = _KINDS[k](out, r, box=walker)
        elif k in ("fixed_wall", "wall_end"):
            out = fixed_wall(out, r, row=wall_row, end=wall_end_at if k == "wall_end" else None)
        else:
            out = _KINDS[k](out, r)
    return out


def damage_sequence(silhouettes: dict[str, list[np.ndarray | None]], kind: str, *, seed: int = 0,
                    truth: dict | None = None) -> dict[str, list[np.ndarray | None]]:
    """Damage every full-frame silhouette of every camera; None frames stay None.

    The second person and the shadow keep one placement per camera over the
    sequence (drawn once per camera), as a bystander or a light would, and
    ``fixed_wall`` one row of the frame (``wall_end`` a row and where it ends); the other damage is drawn afresh per
    frame. ``truth`` (a sequence's truth dict) gives ``cut_limb`` the true joints.
    """
    out = {}
    for c, (cam, frames) in enumerate(silhouettes.items()):
        rng = np.random.default_rng([seed, c])
        steady = int(rng.integers(2**31))  # one draw per camera for placement-like damage
        walled = "fixed_wall" in kind or "wall_end" in kind
        row = _wall_row(frames, np.random.default_rng([seed, c, steady, 1])) if walled else None
        end = _wall_end(frames, np.random.default_rng([seed, c, steady, 2])) if "wall_end" in kind else None
        damaged = []
        for t, sil in enumerate(frames):
            if sil is None:
                damaged.append(None)
                continue
            j2d = None
            if truth is not None:
                j2d = np.asarray(truth["frames"][t]["joints2d"].get(cam, np.full((13, 2), np.nan)), float)
            damaged.append(damage(sil, kind, np.random.default_rng([seed, c, t]), j2d,
                                  steady_rng=np.random.default_rng([seed, c, steady]), wall_row=row,
                                  wall_end_at=end))
        out[cam] = damaged
    return out


def detector_keypoints(joints2d: np.ndarray, rng: np.random.Generator, *, noise_share: float = 0.01,
                       gross: float = 0.02, gross_share: tuple[float, float] = (0.1, 0.2),
                       missed: float = 0.05) -> np.ndarray:
    """Exact 2D joints (C, T, 13, 2) as a pose detector would give them: Gaussian noise of ``noise_share``
    of the walker's image height (per camera and frame), ``gross`` of the joints displaced by
    ``gross_share`` of it in a random direction (a joint put on another limb), ``missed`` of them NaN."""
    j = np.asarray(joints2d, float)
    height = np.ptp(j[..., 1], axis=-1)[..., None, None]  # (C, T, 1, 1)
    out = j + rng.normal(0.0, 1.0, j.shape) * noise_share * height
    far = (rng.random(j.shape[:-1]) < gross) * rng.uniform(*gross_share, j.shape[:-1])
    ang = rng.uniform(0.0, 2 * np.pi, j.shape[:-1])
    out += far[..., None] * height * np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    out[rng.random(j.shape[:-1]) < missed] = np.nan
    return out
