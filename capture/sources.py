"""Frame sources behind one interface, and the ``--source SPEC`` factory.

Implementing a source
---------------------
Subclass :class:`FrameSource` and implement ``__iter__`` (and ``close`` if
you hold resources). The contract:

* ``__iter__`` yields :class:`Frame` objects, in capture order, until the
  source is exhausted (files) or closed; a live source may block until the
  next frame. Iterate once: a second ``iter()`` may continue or restart.
* ``Frame.image`` is ``(H, W, 3)`` uint8 BGR, C-contiguous; every frame of a
  source has the same size. ``Frame.mask`` is the ground-truth silhouette,
  ``(H, W)`` uint8 0/255, or None when unknown (only synthetic and test
  sources know it).
* The scene need not be empty: the agent bootstraps the background from the
  temporal median of frames sampled over the first seconds. A recorded source
  that can be re-read implements ``sample(indices)`` (the frames at those
  indices, read independently of iteration), so segmentation starts at frame
  0; otherwise (live sources) the first ``SegmentSettings.warmup_frames`` are
  collected at start-up and not segmented.
* ``Frame.index`` counts frames from 0 (or the camera's hardware frame
  counter); a gap in indices means frames were lost before reaching us.
* ``Frame.timestamp_ns`` is the capture time as :func:`time.time_ns` (wall
  clock, so hosts synchronised by NTP/PTP can be compared).
* Class or instance attributes:
  ``fps`` — nominal frames per second, or None if unknown;
  ``live`` — True when the source delivers at the sensor's own rate (devices,
  GStreamer, GenICam). Recorded and synthetic sources set False and yield as
  fast as they can; consumers replay them in real time with :func:`paced`,
  which re-stamps ``timestamp_ns`` at release as if a camera had just fired;
  ``hardware_sync`` — True when frames of different cameras align by
  ``index`` (hardware trigger, or recordings of a synchronised rig), False
  when they align by ``timestamp_ns``;
  ``size`` — ``(width, height)`` if known before the first frame, else None.
* ``close()`` releases the device or file and is idempotent; sources are
  context managers (``with make_source(spec) as src:``).
* ``from_spec(spec)`` (classmethod) builds the source from the text after
  ``scheme:``; raise :class:`SourceError` with a clear message for bad specs.

Spec syntax
-----------
``PATH`` (video file or folder of images), ``device:N``, ``gst:PIPELINE``,
``genicam:CTI_PATH[,serial=S][,trigger=1]``, ``synthetic:k=v,...``. Files
and folders accept options after ``?``: ``clip.mp4?loop=1&sync=time``.
"""

from __future__ import annotations

import abc
import os
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Self

import cv2
import numpy as np

__all__ = [
    "DeviceSource",
    "FolderSource",
    "Frame",
    "FrameSource",
    "GenICamSource",
    "SourceError",
    "VideoFileSource",
    "make_source",
    "paced",
    "parse_options",
    "read_plate",
]

IMAGE_SUFFIXES = frozenset({".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm"})
# An image of the empty scene beside a video <camera>.<ext>: <camera>.background<suffix>
# (capture.refine.plate_for; jobs take it beside each uploaded video).
PLATE_SUFFIXES = (".background.png", ".background.jpg", ".background.jpeg")


class SourceError(ValueError):
    """A source spec or device that cannot be used; the message says why."""


def read_plate(path: str | os.PathLike, size: tuple[int, int] | None) -> np.ndarray:
    """An image of the empty scene (BGR uint8) for a source of frame ``size`` (width, height; None:
    unknown, not checked): the segmenter's background (:class:`capture.segment.Segmenter`).

    Raises :class:`SourceError` naming the file when it cannot be read or is not ``size``.
    """
    name = Path(path).name
    plate = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if plate is None:
        raise SourceError(f"background image {name} cannot be read as an image")
    if size is not None and (plate.shape[1], plate.shape[0]) != tuple(size):
        raise SourceError(f"background image {name} is {plate.shape[1]}x{plate.shape[0]}, the frames "
                          f"{size[0]}x{size[1]}")
    return plate


@dataclass(slots=True)
class Frame:
    """One captured image; see the module docstring for the contract."""

    image: np.ndarray
    index: int
    timestamp_ns: int
    mask: np.ndarray | None = None

    @property
    def size(self) -> tuple[int, int]:
        """``(width, height)``."""
        return self.image.shape[1], self.image.shape[0]


class FrameSource(abc.ABC):
    """Base class of every frame source (module docstring: the full contract)."""

    fps: float | None = None
    live: bool = False
    hardware_sync: bool = False
    size: tuple[int, int] | None = None

    @abc.abstractmethod
    def __iter__(self) -> Iterator[Frame]:
        """Yield frames in capture order until exhausted or closed."""

    def close(self) -> None:
        """Release resources; safe to call twice."""

    def frame_count(self) -> int | None:
        """Frames in a recording that can be re-read, else None (live, unknown)."""
        return None

    def sample(self, indices: Iterable[int]) -> list[np.ndarray]:
        """The images at ``indices`` (ascending), read again from the start without
        disturbing iteration; only sources with a :meth:`frame_count`."""
        raise NotImplementedError(f"{type(self).__name__} cannot be re-read")

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> None:
        self.close()


def paced(frames: Iterable[Frame], fps: float) -> Iterator[Frame]:
    """Release ``frames`` at ``fps`` in real time, re-stamping ``timestamp_ns``.

    Frame ``k`` is due at ``start + k / fps``; if the consumer falls behind,
    frames are released at once (not skipped) so every frame is still seen.
    """
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    period = 1e9 / fps
    start = None
    for k, frame in enumerate(frames):
        now = time.monotonic_ns()
        if start is None:
            start = now
        wait = start + k * period - now
        if wait > 0:
            time.sleep(wait / 1e9)
        frame.timestamp_ns = time.time_ns()
        yield frame


def _bgr(image: np.ndarray) -> np.ndarray:
    """Any 8-bit grey/BGR/BGRA image as contiguous ``(H, W, 3)`` BGR."""
    if image.dtype != np.uint8:
        image = cv2.convertScaleAbs(image, alpha=255.0 / max(1, int(image.max())))
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return np.ascontiguousarray(image)


def parse_options(text: str, *, sep: str = ",") -> dict[str, str]:
    """``"a=1,b=x"`` -> ``{"a": "1", "b": "x"}``; a bare word maps to ``""``."""
    out: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in text.split(sep))):
        key, _, value = item.partition("=")
        out[key.strip()] = value.strip()
    return out


def _flag(options: dict[str, str], name: str, default: bool) -> bool:
    value = options.pop(name, None)
    if value is None:
        return default
    if value.lower() in ("", "1", "true", "yes", "on"):
        return True
    if value.lower() in ("0", "false", "no", "off"):
        return False
    raise SourceError(f"option {name}={value!r} is not a boolean")


def _sync(options: dict[str, str], default: bool) -> bool:
    value = options.pop("sync", None)
    if value is None:
        return default
    if value not in ("index", "time"):
        raise SourceError(f"sync must be 'index' or 'time', got {value!r}")
    return value == "index"


def _no_leftovers(options: dict[str, str], what: str) -> None:
    if options:
        raise SourceError(f"unknown {what} option(s): {', '.join(sorted(options))}")


class _CaptureSource(FrameSource):
    """Shared reading loop over a ``cv2.VideoCapture``."""

    def __init__(self, cap: cv2.VideoCapture, what: str) -> None:
        if not cap.isOpened():
            raise SourceError(f"cannot open {what}")
        self._cap = cap
        self._what = what
        fps = cap.get(cv2.CAP_PROP_FPS)
        self.fps = fps if fps and fps > 0 else None
        w, h = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH)), int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.size = (w, h) if w > 0 and h > 0 else None
        self._index = 0

    def _read(self) -> np.ndarray | None:
        ok, image = self._cap.read()
        return _bgr(image) if ok and image is not None else None

    def __iter__(self) -> Iterator[Frame]:
        while self._cap is not None:
            image = self._read()
            stamp = time.time_ns()
            if image is None:
                return
            yield Frame(image, self._index, stamp)
            self._index += 1

    def close(self) -> None:
        if self._cap is not None:
            self._cap.release()
            self._cap = None


class VideoFileSource(_CaptureSource):
    """A recorded video file; ``loop=1`` rewinds at the end. Aligns by index by default."""

    live = False

    def __init__(self, path: str | os.PathLike[str], *, loop: bool = False,
                 hardware_sync: bool = True) -> None:
        path = Path(path)
        if not path.is_file():
            raise SourceError(f"video file not found: {path}")
        super().__init__(cv2.VideoCapture(str(path)), f"video file {path}")
        self.path = path
        self.loop = loop
        self.hardware_sync = hardware_sync

    def frame_count(self) -> int | None:
        n = 0 if self._cap is None else int(self._cap.get(cv2.CAP_PROP_FRAME_COUNT))  # a header field
        return n if n > 0 else None

    def sample(self, indices: Iterable[int]) -> list[np.ndarray]:
        keep = set(indices)
        out: list[np.ndarray] = []
        cap = cv2.VideoCapture(str(self.path))  # a second reader: iteration is not disturbed
        try:
            for k in range(max(keep) + 1 if keep else 0):  # sequential: seeking is inexact
                if not cap.grab():
                    break
                if k in keep:
                    ok, image = cap.retrieve()
                    if ok:
                        out.append(_bgr(image))
        finally:
            cap.release()
        return out

    def _read(self) -> np.ndarray | None:
        image = super()._read()
        if image is None and self.loop and self._index > 0 and self._cap is not None:
            self._cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            image = super()._read()
        return image


class DeviceSource(_CaptureSource):
    """A live OpenCV device (``device:N``) or GStreamer pipeline (``gst:...``).

    USB cameras via V4L2, GigE cameras via their GStreamer plugin (e.g.
    ``aravissrc``). The pipeline must end in ``appsink``.
    """

    live = True

    def __init__(self, target: int | str, *, api: int = cv2.CAP_ANY,
                 width: int | None = None, height: int | None = None,
                 fps: float | None = None) -> None:
        cap = cv2.VideoCapture(target, api)
        if cap.isOpened():
            cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # newest frame: a stale buffer is latency
            for prop, value in ((cv2.CAP_PROP_FRAME_WIDTH, width),
                                (cv2.CAP_PROP_FRAME_HEIGHT, height), (cv2.CAP_PROP_FPS, fps)):
                if value:
                    cap.set(prop, value)
        what = f"device {target}" if isinstance(target, int) else f"GStreamer pipeline {target!r}"
        super().__init__(cap, what)
        self.hardware_sync = False


class FolderSource(FrameSource):
    """A folder of images read in name order (e.g. ``000000.png``...)."""

    live = False

    def __init__(self, path: str | os.PathLike[str], *, fps: float | None = None,
                 loop: bool = False, hardware_sync: bool = True) -> None:
        path = Path(path)
        self._files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not self._files:
            raise SourceError(f"no images ({', '.join(sorted(IMAGE_SUFFIXES))}) in {path}")
        self.fps = fps
        self.loop = loop
        self.hardware_sync = hardware_sync
        self._closed = False

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        while not self._closed:
            for file in self._files:
                if self._closed:
                    return
                image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
                if image is None:
                    raise SourceError(f"cannot read image {file}")
                yield Frame(_bgr(image), index, time.time_ns())
                index += 1
            if not self.loop:
                return

    def frame_count(self) -> int | None:
        return len(self._files)

    def sample(self, indices: Iterable[int]) -> list[np.ndarray]:
        return [_bgr(cv2.imread(str(self._files[k]), cv2.IMREAD_UNCHANGED))
                for k in sorted(set(indices)) if k < len(self._files)]

    def close(self) -> None:
        self._closed = True


class GenICamSource(FrameSource):
    """A GenICam camera through ``harvesters`` and a GenTL producer (``.cti``).

    This is how Point Grey/FLIR Dragonfly-class cameras are reached. With
    ``trigger=1`` the camera runs on its hardware trigger line, frames carry
    the camera's frame id and align by index. Needs the ``genicam`` extra.
    """

    live = True

    def __init__(self, cti: str | os.PathLike[str], *, serial: str | None = None,
                 trigger: bool = False, timeout_s: float = 2.0) -> None:
        try:
            from harvesters.core import Harvester
        except ImportError:
            raise SourceError("genicam sources need the optional 'harvesters' package: "
                              "pip install 'posecal[genicam]'") from None
        if not Path(cti).is_file():
            raise SourceError(f"GenTL producer not found: {cti}")
        self._closed = False
        self._h = Harvester()
        self._h.add_file(str(cti))
        self._h.update()
        try:
            self._ia = self._h.create({"serial_number": serial} if serial else 0)
        except (IndexError, ValueError) as exc:
            self._h.reset()
            raise SourceError(f"no GenICam camera {serial or '#0'} via {cti}: {exc}") from None
        nodes = self._ia.remote_device.node_map
        if trigger:  # SFNC names: start each frame on the rising edge of input line 0
            try:
                nodes.TriggerSelector.value = "FrameStart"
                nodes.TriggerMode.value = "On"
                nodes.TriggerSource.value = "Line0"
            except Exception as exc:  # genicam raises its own types per node
                self.close()
                raise SourceError(f"camera does not accept a hardware trigger: {exc}") from None
        self.hardware_sync = trigger
        try:
            self.fps = float(nodes.AcquisitionFrameRate.value)
        except Exception:  # not every camera exposes the node
            self.fps = None
        self._timeout = timeout_s
        self._ia.start()

    def __iter__(self) -> Iterator[Frame]:
        index = 0
        while not self._closed:
            try:
                buffer = self._ia.fetch(timeout=self._timeout)
            except Exception as exc:  # harvesters raises its own TimeoutException
                if self._closed:
                    return
                if type(exc).__name__.startswith("Timeout"):
                    continue
                raise
            with buffer:
                stamp = time.time_ns()
                comp = buffer.payload.components[0]
                channels = comp.num_components_per_pixel or 1
                raw = comp.data.reshape(comp.height, comp.width, int(channels)).squeeze()
                fmt = str(comp.data_format)
                if fmt.startswith("Bayer"):
                    code = {"BayerRG8": cv2.COLOR_BayerRG2BGR, "BayerBG8": cv2.COLOR_BayerBG2BGR,
                            "BayerGR8": cv2.COLOR_BayerGR2BGR, "BayerGB8": cv2.COLOR_BayerGB2BGR}
                    image = cv2.cvtColor(raw, code.get(fmt, cv2.COLOR_BayerRG2BGR))
                elif fmt.startswith("RGB"):
                    image = cv2.cvtColor(raw, cv2.COLOR_RGB2BGR)
                else:
                    image = _bgr(raw.copy())
                frame_id = getattr(buffer, "frame_id", None)
                idx = int(frame_id) if self.hardware_sync and frame_id is not None else index
            yield Frame(image, idx, stamp)
            index += 1

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._ia.stop()
            self._ia.destroy()
            self._h.reset()


def _video_or_folder(spec: str) -> FrameSource:
    path_text, _, query = spec.partition("?")
    options = parse_options(query, sep="&")
    loop = _flag(options, "loop", False)
    sync = _sync(options, True)
    path = Path(path_text).expanduser()
    if path.is_dir():
        fps = float(options.pop("fps")) if "fps" in options else None
        _no_leftovers(options, "folder")
        return FolderSource(path, fps=fps, loop=loop, hardware_sync=sync)
    _no_leftovers(options, "video file")
    if not path.exists():
        raise SourceError(f"no such file or folder: {path}")
    return VideoFileSource(path, loop=loop, hardware_sync=sync)


def _device(rest: str) -> FrameSource:
    index, _, opts = rest.partition(",")
    try:
        device = int(index)
    except ValueError:
        raise SourceError(f"device:N needs an integer index, got {index!r}") from None
    options = parse_options(opts)
    try:
        kwargs = {k: int(options.pop(k)) for k in ("width", "height") if k in options}
        fps = float(options.pop("fps")) if "fps" in options else None
    except ValueError as exc:
        raise SourceError(f"bad device option: {exc}") from None
    _no_leftovers(options, "device")
    return DeviceSource(device, fps=fps, **kwargs)


def _gstreamer(pipeline: str) -> FrameSource:
    build = cv2.getBuildInformation()
    line = next((ln for ln in build.splitlines() if ln.strip().startswith("GStreamer:")), "")
    if "YES" not in line:
        raise SourceError("this OpenCV build has no GStreamer support (opencv-python-headless "
                          "from PyPI has none); build OpenCV with GStreamer or use device:N")
    if not pipeline.strip():
        raise SourceError("gst: needs a pipeline ending in appsink")
    return DeviceSource(pipeline, api=cv2.CAP_GSTREAMER)


def _genicam(rest: str) -> FrameSource:
    cti, _, opts = rest.partition(",")
    options = parse_options(opts)
    serial = options.pop("serial", None)
    trigger = _flag(options, "trigger", False)
    _no_leftovers(options, "genicam")
    return GenICamSource(cti or os.environ.get("GENICAM_GENTL64_PATH", ""),
                         serial=serial, trigger=trigger)


def _synthetic(rest: str) -> FrameSource:
    try:
        from .synthetic import SyntheticSource  # imports the renderer only when asked for
    except ImportError as exc:
        raise SourceError(f"the synthetic camera is not available: {exc}") from None
    return SyntheticSource.from_spec(rest)


_SCHEMES = {
    "device": _device,
    "gst": lambda rest: _gstreamer(rest),
    "genicam": _genicam,
    "synthetic": _synthetic,
}


def make_source(spec: str) -> FrameSource:
    """Build a source from ``--source SPEC`` (module docstring: the syntax)."""
    spec = spec.strip()
    if not spec:
        raise SourceError("empty source spec")
    scheme, sep, rest = spec.partition(":")
    if sep and scheme in _SCHEMES:
        return _SCHEMES[scheme](rest)
    # A Windows drive letter or a path with a colon is still a path; a word that
    # looks like a scheme but is neither a known one nor an existing path is not.
    if sep and scheme.isidentifier() and not Path(spec.partition("?")[0]).exists():
        known = ", ".join(f"{s}:" for s in _SCHEMES)
        raise SourceError(f"unknown source scheme {scheme!r} (expected a path or one of {known})")
    return _video_or_folder(spec)
