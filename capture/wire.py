"""The posecal wire format: silhouette and feedback messages on Zenoh.

This is the one module that defines, versions and validates what travels on
the key space (``DESIGN.md``, "Wire")::

    posecal/<rig>/<camera>/silhouette   capture -> service   SilhouetteMessage
    posecal/<rig>/<camera>/feedback     service -> capture   FeedbackMessage
    posecal/<rig>/estimate              service -> anyone    (JSON result)

Every payload is one self-contained envelope, so a recorded payload can be
validated and replayed without Zenoh metadata::

    offset  size  field
    0       4     magic  b"PCAL"
    4       1     version (WIRE_VERSION)
    5       1     kind    (1 = silhouette, 2 = feedback)
    6       4     header length N, unsigned big-endian
    10      N     header: UTF-8 JSON object (fields below)
    10+N    ...   PNG image of the crop (absent when the box is empty)

:func:`decode` rejects anything malformed with a :class:`WireError` whose
message says what was wrong; receivers count and log it and go on.
"""

from __future__ import annotations

import dataclasses
import json
import re
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar

import cv2
import numpy as np

__all__ = [
    "WIRE_VERSION",
    "Box",
    "FeedbackMessage",
    "Quality",
    "SilhouetteMessage",
    "WireError",
    "decode",
    "encode",
    "estimate_key",
    "feedback_key",
    "keypoints_for_frame",
    "parse_key",
    "silhouette_key",
]

WIRE_VERSION = 1
MAGIC = b"PCAL"
_PREFIX = struct.Struct(">4sBBI")  # magic, version, kind, header length
_MAX_HEADER = 64 * 1024
MAX_IMAGE_SIDE = 8192  # width or height of a frame (8K)
MAX_IMAGE_PIXELS = 7680 * 4320  # width x height (8K UHD): a full-frame canvas stays below 34 MB
_MAX_SIDE = MAX_IMAGE_SIDE
_MAX_INT = (1 << 63) - 1  # integers travel as int64 (nanoseconds, indices, sequence numbers)
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_MAX_CANDIDATES = 1 << 16
_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_ROOT = "posecal"
N_JOINTS = 13  # estimator.joints.N_JOINTS, not imported: the wire stays light for any subscriber
_MAX_PIXEL = 1e6  # a keypoint coordinate beyond it is not one (and a 400-digit integer is no float)

Sync = Literal["index", "time"]
T = TypeVar("T")


class WireError(ValueError):
    """A payload or key that is not a valid posecal message; ``str()`` is the reason.

    ``code`` is its kind, one of a few fixed words (a metric label: ``envelope``,
    ``header``, ``field``, ``image``, ``key``); the reason itself may quote the payload.
    """

    def __init__(self, reason: str, code: str = "field") -> None:
        super().__init__(reason)
        self.code = code


# --------------------------------------------------------------------------- keys


def _check_name(what: str, name: str, *, wildcard: bool) -> str:
    if wildcard and name in ("*", "**"):
        return name
    if not isinstance(name, str) or not _NAME.match(name):
        raise WireError(f"{what} must match {_NAME.pattern}, got {name!r:.80}", "key")
    return name


def silhouette_key(rig: str, camera: str) -> str:
    """``posecal/<rig>/<camera>/silhouette``; ``"*"`` is allowed for subscribing."""
    return "/".join((_ROOT, _check_name("rig", rig, wildcard=True),
                     _check_name("camera", camera, wildcard=True), "silhouette"))


def feedback_key(rig: str, camera: str) -> str:
    """``posecal/<rig>/<camera>/feedback``; ``"*"`` is allowed for subscribing."""
    return "/".join((_ROOT, _check_name("rig", rig, wildcard=True),
                     _check_name("camera", camera, wildcard=True), "feedback"))


def estimate_key(rig: str) -> str:
    """``posecal/<rig>/estimate``, where the service publishes each window's result."""
    return f"{_ROOT}/{_check_name('rig', rig, wildcard=True)}/estimate"


def parse_key(key: str) -> tuple[str, str | None, str]:
    """Split a concrete key into ``(rig, camera, kind)``; camera is None for estimates."""
    parts = str(key).split("/")
    if len(parts) == 4 and parts[0] == _ROOT and parts[3] in ("silhouette", "feedback"):
        return (_check_name("rig", parts[1], wildcard=False),
                _check_name("camera", parts[2], wildcard=False), parts[3])
    if len(parts) == 3 and parts[0] == _ROOT and parts[2] == "estimate":
        return _check_name("rig", parts[1], wildcard=False), None, "estimate"
    raise WireError(f"not a posecal key: {key!r:.200}", "key")


# -------------------------------------------------------------------------- messages


@dataclass(frozen=True, slots=True)
class Box:
    """Axis-aligned box in full-frame pixels: top-left ``(x, y)``, size ``(w, h)``."""

    x: int
    y: int
    w: int
    h: int

    @property
    def empty(self) -> bool:
        return self.w == 0 or self.h == 0

    def slices(self) -> tuple[slice, slice]:
        """``image[box.slices()]`` is the crop."""
        return slice(self.y, self.y + self.h), slice(self.x, self.x + self.w)

    def paste(self, crop: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
        """``crop`` (of shape ``(h, w)``) at this box in a zero ``(height, width)`` canvas."""
        out = np.zeros(image_size[::-1], crop.dtype)
        if not self.empty:
            out[self.slices()] = crop
        return out


def _check_frame(box: Box, image_size: tuple[int, int]) -> None:
    """The image within the size limits and the box inside it (before a crop is decoded)."""
    width, height = image_size
    if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE) or width * height > MAX_IMAGE_PIXELS:
        raise WireError(f"image_size must be positive, each side <= {MAX_IMAGE_SIDE} and at most "
                        f"{MAX_IMAGE_PIXELS} pixels, got {image_size}", "image")
    if min(box.x, box.y, box.w, box.h) < 0 or box.x + box.w > width or box.y + box.h > height:
        raise WireError(f"box {dataclasses.astuple(box)} is not inside the image {image_size}")


def png_size(head: bytes) -> tuple[int, int] | None:
    """Width and height from a PNG's first 24 bytes (signature and ``IHDR``), without
    decoding it; None if they are not a PNG header."""
    if len(head) < 24 or head[:8] != _PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", head[16:24])


def _png_crop(png: bytes, box: Box) -> np.ndarray:
    """Decode the crop's PNG once its header says it is the box's size (a header claiming
    100000 x 100000 pixels is refused before anything is allocated)."""
    size = png_size(png)
    if size is None:
        raise WireError("crop is not a decodable PNG (no PNG header)", "image")
    width, height = size
    if (width, height) != (box.w, box.h):
        raise WireError(f"crop PNG of {width}x{height} (its header) does not match box size "
                        f"{box.w}x{box.h}", "image")
    try:
        mask = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise WireError(f"crop is not a decodable PNG: {str(exc).strip().splitlines()[-1]:.120}", "image") from None
    if mask is None:
        raise WireError("crop is not a decodable PNG", "image")
    return mask


def _crop_fields(rig: str, camera: str, frame_index: int, box: Box,
                 image_size: tuple[int, int], mask: np.ndarray) -> None:
    """Checks shared by both message kinds; raise WireError with the reason."""
    _check_name("rig", rig, wildcard=False)
    _check_name("camera", camera, wildcard=False)
    if frame_index < 0:
        raise WireError(f"frame_index must be >= 0, got {frame_index}")
    _check_frame(box, image_size)
    if mask.dtype != np.uint8 or mask.ndim != 2:
        raise WireError(f"mask must be a 2-D uint8 array, got {mask.dtype} {mask.shape}")
    if mask.shape != (box.h, box.w) and not (box.empty and mask.size == 0):
        raise WireError(f"mask shape {mask.shape} does not match box size {(box.h, box.w)}")


def _near_frame(points: np.ndarray, image_size: tuple[int, int]) -> np.ndarray:
    """Per joint: placed (no NaN) and within an image's size of the frame (a detector puts a joint
    just outside it at times; not across the room)."""
    size = np.asarray(image_size, float)
    with np.errstate(invalid="ignore"):
        return np.all(np.abs(points - size / 2) <= 1.5 * size, axis=1)


def _check_keypoints(points: np.ndarray, image_size: tuple[int, int]) -> None:
    """Joints of a detector: (13, 2) float64, NaN rows for missed joints, the others finite and near
    the frame (:func:`_near_frame`)."""
    if not isinstance(points, np.ndarray) or points.shape != (N_JOINTS, 2) or points.dtype != np.float64:
        raise WireError(f"keypoints must be a float64 array of shape ({N_JOINTS}, 2), got "
                        f"{getattr(points, 'dtype', type(points).__name__)} {getattr(points, 'shape', '')}")
    missed = np.isnan(points).all(axis=1)
    if not np.all(missed | _near_frame(points, image_size)):
        raise WireError(f"keypoints must be NaN pairs or finite pixels within the image's size of the "
                        f"{image_size} frame")


def keypoints_for_frame(points: np.ndarray | None, image_size: tuple[int, int]) -> np.ndarray | None:
    """A detector's (13, 2) joints as :class:`SilhouetteMessage` takes them: joints that are NaN or far
    outside the frame are missed; None when none is left."""
    if points is None:
        return None
    points = np.asarray(points, np.float64).reshape(N_JOINTS, 2)
    near = _near_frame(points, image_size)
    return np.where(near[:, None], points, np.nan) if near.any() else None


def _keypoints(header: dict[str, Any], name: str) -> np.ndarray:
    """``[[x, y] | null] * 13`` -> (13, 2) float, NaN where null."""
    value = header.get(name)
    if not isinstance(value, list) or len(value) != N_JOINTS or any(
            v is not None and (not isinstance(v, list) or len(v) != 2
                               or any(type(c) not in (int, float) or not abs(c) <= _MAX_PIXEL for c in v))
            for v in value):
        raise WireError(f"header field {name!r} must be a list of {N_JOINTS} [x, y] pairs of numbers or nulls, "
                        f"got {value!r:.80}")
    points = np.array([[np.nan, np.nan] if v is None else v for v in value], float)
    return None if np.isnan(points).all() else points


@dataclass(frozen=True, slots=True)
class Quality:
    """A camera's segmentation quality over its agent's recent frames (``AgentStats``).

    ``walker_fraction``: share of segmented frames in which a walker was found,
    in [0, 1]; ``area_median``: median silhouette area in full-frame pixels
    (0 = no walker yet); ``stability``: median box IoU of consecutive
    silhouettes in [0, 1] (1 = steady, low = flickering or jumping), None until
    two consecutive frames had a walker.
    """

    walker_fraction: float
    area_median: float
    stability: float | None = None

    def __post_init__(self) -> None:
        for name, high in (("walker_fraction", 1), ("area_median", _MAX_SIDE ** 2), ("stability", 1)):
            value = getattr(self, name)
            if value is None and name == "stability":
                continue
            # type() excludes bool; the range test excludes NaN and infinity (json reads both)
            if type(value) not in (int, float) or not 0 <= value <= high:
                raise WireError(f"quality.{name} must be a number in [0, {high}], got {value!r}")


@dataclass(frozen=True, slots=True)
class SilhouetteMessage:
    """One segmented frame from one camera (capture -> service).

    ``mask`` is the crop, uint8 0/255 of shape ``(box.h, box.w)``; an empty
    box (nothing segmented) carries a ``(0, 0)`` mask so every processed frame
    is reported. ``epoch_ns`` is the agent's start time and ``seq`` counts its
    messages from 0: a new epoch means the agent restarted. ``sync`` tells how
    frames of different cameras align: by ``frame_index`` (hardware-triggered
    or recorded rigs) or by ``capture_ns``.

    Optional, None = not reported (older agents; left out of the header):
    ``n_candidates`` is the number of person-sized components in this frame
    (> 1: several people in view, the tracked walker is the one sent), on every
    message because it belongs to the frame; ``quality`` is the agent's
    :class:`Quality` over its recent frames, sent only every few messages
    (``AgentSettings.quality_every``): its medians over hundreds of frames move
    slowly, so computing them per frame would cost the latency path for
    nothing, and a receiver keeps the latest. ``keypoints`` are a pose
    detector's joints in this frame, ``(13, 2)`` full-frame pixels in posecal's
    joint order (:data:`estimator.joints.JOINT_NAMES`), NaN where missed (JSON:
    ``null`` per joint): the service's live rig calibrates from them instead of
    measuring postures on the silhouettes (docs/SERVICE.md, "The live rig").
    ``track_id`` numbers the person the agent's track is on: 0 from its start,
    one more each time its look back moves the track onto another person
    (:class:`capture.choose.LiveChoice`) and each time its track, lost, starts
    again on someone else (:func:`capture.live.same_person`): the frames of an
    earlier track followed someone else, and the service leaves them out of a
    window that holds frames of the later one (docs/SERVICE.md, "Live windows").
    ``track_from``, with a ``track_id`` of 1 or more, is the first frame the
    earlier track followed someone else before that move (the look back's
    :attr:`~capture.choose.LiveChoice.since`): the service leaves the earlier
    tracks' frames from there on out of every window, and estimates again
    the windows it published with them.
    """

    KIND: ClassVar[int] = 1

    rig: str
    camera: str
    frame_index: int
    capture_ns: int
    box: Box
    image_size: tuple[int, int]  # (width, height) of the full frame
    epoch_ns: int
    seq: int
    mask: np.ndarray = dataclasses.field(repr=False, compare=False)
    sync: Sync = "time"
    publish_ns: int = 0
    n_candidates: int | None = None
    quality: Quality | None = None
    keypoints: np.ndarray | None = dataclasses.field(default=None, repr=False, compare=False)
    track_id: int | None = None
    track_from: int | None = None

    def __post_init__(self) -> None:
        _crop_fields(self.rig, self.camera, self.frame_index, self.box, self.image_size, self.mask)
        if self.keypoints is not None:
            _check_keypoints(self.keypoints, self.image_size)
            frozen = np.array(self.keypoints)  # a copy nobody can change into a non-JSON number later
            frozen.flags.writeable = False
            object.__setattr__(self, "keypoints", frozen)
        if self.n_candidates is not None and (type(self.n_candidates) is not int
                                              or not 0 <= self.n_candidates <= _MAX_CANDIDATES):
            raise WireError(f"n_candidates must be an integer in [0, {_MAX_CANDIDATES}], "
                            f"got {self.n_candidates!r}")
        if self.quality is not None and self.quality.area_median > self.image_size[0] * self.image_size[1]:
            raise WireError(f"quality.area_median {self.quality.area_median} exceeds the image "
                            f"{self.image_size}")
        if self.track_id is not None and (type(self.track_id) is not int or self.track_id < 0):
            raise WireError(f"track_id must be an integer >= 0, got {self.track_id!r}")
        if self.track_from is not None and (
                type(self.track_from) is not int or not 0 <= self.track_from <= self.frame_index
                or not self.track_id):
            raise WireError(f"track_from must be a frame index from 0 to frame_index ({self.frame_index}) "
                            f"with a track_id of 1 or more, got {self.track_from!r} (track_id {self.track_id!r})")
        if self.capture_ns <= 0 or self.epoch_ns <= 0:
            raise WireError("capture_ns and epoch_ns must be positive nanoseconds")
        if self.seq < 0:
            raise WireError(f"seq must be >= 0, got {self.seq}")
        if self.sync not in ("index", "time"):
            raise WireError(f"sync must be 'index' or 'time', got {self.sync!r}")
        if self.mask.size and np.any((self.mask != 0) & (self.mask != 255)):
            raise WireError("silhouette mask must be binary 0/255")

    def full_mask(self) -> np.ndarray:
        """The silhouette pasted into a full-frame ``(height, width)`` canvas."""
        return self.box.paste(self.mask, self.image_size)


@dataclass(frozen=True, slots=True)
class FeedbackMessage:
    """A prior mask for one camera's segmenter (service -> capture, paper §7.1).

    ``mask`` has shape ``(box.h, box.w)``, uint8, 0 = no opinion and 255 =
    surely the walker; it applies to frames from ``frame_index`` on (the
    service may predict a future frame). ``issued_ns`` is the sender's wall
    clock when it was sent (0 = unknown); ``epoch_ns`` the epoch of the agent
    run whose frame indices it refers to (0 = any): an agent that restarted
    ignores priors meant for its previous run.
    """

    KIND: ClassVar[int] = 2

    rig: str
    camera: str
    frame_index: int
    box: Box
    image_size: tuple[int, int]
    mask: np.ndarray = dataclasses.field(repr=False, compare=False)
    issued_ns: int = 0
    epoch_ns: int = 0

    def __post_init__(self) -> None:
        _crop_fields(self.rig, self.camera, self.frame_index, self.box, self.image_size, self.mask)

    def full_mask(self) -> np.ndarray:
        """The prior pasted into a full-frame ``(height, width)`` canvas."""
        return self.box.paste(self.mask, self.image_size)


Message = SilhouetteMessage | FeedbackMessage
_KINDS: dict[int, type[SilhouetteMessage] | type[FeedbackMessage]] = {
    SilhouetteMessage.KIND: SilhouetteMessage,
    FeedbackMessage.KIND: FeedbackMessage,
}


# ------------------------------------------------------------------------- encoding


def _header_value(value: Any) -> Any:
    """A field as JSON: boxes as [x, y, w, h], structs as objects without their None fields."""
    if isinstance(value, Box):
        return dataclasses.astuple(value)
    if dataclasses.is_dataclass(value):
        return {k: v for k, v in dataclasses.asdict(value).items() if v is not None}
    if isinstance(value, np.ndarray):  # keypoints: a pair per joint, null where missed
        return [None if np.isnan(p).any() else [round(float(c), 2) for c in p] for p in value]
    return value


def encode(msg: Message, *, png_compression: int = 1) -> bytes:
    """Serialise a message into one envelope (see the module docstring).

    ``png_compression`` (0-9) trades CPU for bytes; 1 is fast and binary masks
    compress well anyway. Optional fields that are None are left out.
    """
    header = {field.name: _header_value(getattr(msg, field.name))
              for field in dataclasses.fields(msg)
              if field.name != "mask" and getattr(msg, field.name) is not None}
    head = json.dumps(header, separators=(",", ":")).encode()
    png = b""
    if not msg.box.empty:
        ok, buf = cv2.imencode(".png", msg.mask, [cv2.IMWRITE_PNG_COMPRESSION, png_compression])
        if not ok:
            raise WireError("PNG encoding failed")
        png = buf.tobytes()
    return _PREFIX.pack(MAGIC, WIRE_VERSION, msg.KIND, len(head)) + head + png


def _int(header: dict[str, Any], name: str) -> int:
    value = header.get(name)
    if type(value) is not int or abs(value) > _MAX_INT:  # bool is not a valid int here
        raise WireError(f"header field {name!r} must be an integer (64-bit), got {value!r:.40}")
    return value


def _ints(header: dict[str, Any], name: str, n: int) -> tuple[int, ...]:
    value = header.get(name)
    if not isinstance(value, list) or len(value) != n or any(type(v) is not int or abs(v) > _MAX_INT
                                                             for v in value):
        raise WireError(f"header field {name!r} must be a list of {n} integers, got {value!r:.80}")
    return tuple(value)


def _quality(header: dict[str, Any], name: str) -> Quality:
    value = header.get(name)
    if not isinstance(value, dict):
        raise WireError(f"header field {name!r} must be an object, got {value!r:.80}")
    return Quality(walker_fraction=value.get("walker_fraction"), area_median=value.get("area_median"),
                   stability=value.get("stability"))


def _optional(header: dict[str, Any], name: str, parse: Callable[[dict[str, Any], str], T]) -> T | None:
    """``parse`` the field if the header has it, else None (a field older senders lack)."""
    return parse(header, name) if name in header else None


def _str(header: dict[str, Any], name: str) -> str:
    value = header.get(name)
    if not isinstance(value, str):
        raise WireError(f"header field {name!r} must be a string, got {value!r:.80}")
    return value


def decode(payload: bytes | bytearray | memoryview, *,
           expect: type[Message] | None = None) -> Message:
    """Parse and validate one envelope; raise :class:`WireError` saying why not.

    With ``expect`` set, a message of another kind is rejected too.
    """
    data = bytes(payload)
    if len(data) < _PREFIX.size:
        raise WireError(f"payload too short ({len(data)} bytes)", "envelope")
    magic, version, kind, head_len = _PREFIX.unpack_from(data)
    if magic != MAGIC:
        raise WireError(f"bad magic {magic!r}, expected {MAGIC!r}", "envelope")
    if version != WIRE_VERSION:
        raise WireError(f"unsupported wire version {version}, this build speaks {WIRE_VERSION}", "envelope")
    cls = _KINDS.get(kind)
    if cls is None:
        raise WireError(f"unknown message kind {kind}", "envelope")
    if expect is not None and cls is not expect:
        raise WireError(f"expected a {expect.__name__}, got a {cls.__name__}", "envelope")
    if head_len > _MAX_HEADER or _PREFIX.size + head_len > len(data):
        raise WireError(f"header length {head_len} exceeds the payload ({len(data)} bytes)", "envelope")
    try:
        header = json.loads(data[_PREFIX.size:_PREFIX.size + head_len])
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise WireError(f"header is not JSON: {exc}", "header") from None
    except RecursionError:
        raise WireError("header is not JSON: nested too deeply", "header") from None
    if not isinstance(header, dict):
        raise WireError("header must be a JSON object", "header")

    box = Box(*_ints(header, "box", 4))
    width, height = _ints(header, "image_size", 2)
    _check_frame(box, (width, height))
    png = data[_PREFIX.size + head_len:]
    if box.empty:
        if png:
            raise WireError("empty box but a PNG is attached", "image")
        mask = np.zeros((0, 0), np.uint8)
    else:
        mask = _png_crop(png, box)
    common = dict(rig=_str(header, "rig"), camera=_str(header, "camera"),
                  frame_index=_int(header, "frame_index"), box=box,
                  image_size=(width, height), mask=mask)
    if cls is SilhouetteMessage:
        return SilhouetteMessage(**common, capture_ns=_int(header, "capture_ns"),
                                 epoch_ns=_int(header, "epoch_ns"), seq=_int(header, "seq"),
                                 sync=_str(header, "sync"),  # type: ignore[arg-type]
                                 publish_ns=_int(header, "publish_ns"),
                                 n_candidates=_optional(header, "n_candidates", _int),
                                 quality=_optional(header, "quality", _quality),
                                 keypoints=_optional(header, "keypoints", _keypoints),
                                 track_id=_optional(header, "track_id", _int),
                                 track_from=_optional(header, "track_from", _int))
    return FeedbackMessage(**common, issued_ns=_int(header, "issued_ns"),
                           epoch_ns=_optional(header, "epoch_ns", _int) or 0)
