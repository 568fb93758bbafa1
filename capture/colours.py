"""The walker's colours against the other people's: cutting passers-by off a merged blob.

Background subtraction cannot tell people apart: a passer-by whose blob
touches the walker's (beside, or behind at a distance) is one connected
component with them, and the whole component is kept. On posecal's walker
composited into real footage (``bench/eval_composite.py``) such merges were
the largest error left, 20-64 % of extra area in a third of the cameras
(docs/ROBUSTNESS.md). The passers-by were separate blobs in other frames, so
their colours are known; the walker's are known from the frames in which its
blob had its usual size. This is the colour-model split of the people
trackers (McKenna et al. 2000, "Tracking groups of people"), in its simplest
form:

- two colour histograms (BGR, :data:`BINS` per channel), each a running mean
  over frames with rate ``rate``: the walker's, learned from its whole blob
  in *stable* frames only (area no more than :data:`STABLE` times its median
  over the last detections, so a merged frame does not teach the passer-by's
  colours to the walker's model), and the others', learned from every other
  person-sized component of each frame;
- in every frame, once the walker's model rests on ``frames`` stable frames,
  each pixel of the walker's blob gets the log-ratio of its colour's
  frequency on the walker and among the others, averaged over a square
  window of ``window`` times the blob's height (a passer-by is a region, not
  single pixels); where the average says the colour is ``ratio`` times
  likelier among the others, the pixel is cut;
- a cut region lying wholly in the blob's lowest :data:`FEET` of its height
  is given back: a passer-by reaches above the walker's feet, the walker's
  own shoes in the others' colour (black shoes among passers-by in black) do
  not;
- of what is left, pieces smaller than :data:`PIECE` of the largest are
  dropped (the passer-by's fringe that shared the walker's colours).

Where the walker and the passers-by wear the same colours the evidence is
even and nothing is cut. What can be lost is a small part of the walker above
the feet in a colour the others wear much more (a black belt or hair among
passers-by in black), and walker pieces the cut leaves smaller than
:data:`PIECE` of the largest. The walker's model is reset when a new track
starts (another person). It learns from the track's first three detections
whatever they hold, and from any blob within :data:`STABLE` of the median
area: a passer-by who adds less than that, or who stays joined for more than
about half of the detections the median is taken over
(``SegmentSettings.track_frames``), is learned as the walker's. Measured
(docs/ROBUSTNESS.md): composite IoU and the downstream errors with and
without, and vtest.avi's reference masks (real people, dark clothes like
most passers-by) unchanged.
"""

from __future__ import annotations

import cv2
import numpy as np

from .masks import large_components

__all__ = ["BINS", "FEET", "PIECE", "STABLE", "ColourSplit", "colour_bins"]

_SHIFT = 5
BINS = 256 >> _SHIFT
"""Histogram bins per BGR channel (8, of 32 grey levels each): coarse enough that a few
hundred pixels of a far walker fill the walker's bins, fine enough to tell a shirt
from a coat."""
STABLE = 1.15
"""A blob at most this many times the walker's median area teaches the walker's colours."""
PIECE = 0.2
"""After the cut, pieces smaller than this fraction of the largest are dropped."""
FEET = 0.15
"""Cut regions wholly within this fraction of the blob's height above its lowest row are
kept: the walker's shoes (0.90-1.0 of the blob on the composite walks), not a passer-by."""
_EPS = 1e-3  # frequency floor: a colour never seen on either side is no evidence


def colour_bins(pixels: np.ndarray) -> np.ndarray:
    """Each BGR uint8 pixel's histogram bin (int32, the shape of ``pixels`` without the channels)."""
    q = (pixels >> _SHIFT).astype(np.int32)
    return (q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2]


def _histogram(bins: np.ndarray) -> np.ndarray | None:
    h = np.bincount(bins, minlength=BINS ** 3).astype(np.float64)
    total = h.sum()
    return h / total if total else None


class ColourSplit:
    """Running colour models of the tracked walker and of the other people (module docstring).

    Parameters
    ----------
    ratio : float
        Cut where the windowed colour evidence is this many times likelier
        among the others than on the walker.
    window : float
        Side of the averaging window, as a fraction of the blob's height.
    rate : float
        Running-mean rate of both histograms per frame.
    frames : int
        Stable frames the walker's model must rest on before anything is cut.
    """

    def __init__(self, *, ratio: float = 2.7, window: float = 0.04, rate: float = 0.2, frames: int = 5) -> None:
        self.ratio, self.window, self.rate, self.frames = ratio, window, rate, frames
        self.walker: np.ndarray | None = None  # histograms, BINS**3 frequencies
        self.others: np.ndarray | None = None
        self.learned = 0  # stable frames the walker's histogram rests on

    def reset(self) -> None:
        """Forget the walker (a new track starts); the others' colours stay."""
        self.walker, self.learned = None, 0

    @property
    def ready(self) -> bool:
        """Whether the walker's colours rest on ``frames`` stable frames (cuts and likeness use them)."""
        return self.walker is not None and self.learned >= self.frames

    def likeness(self, pixels: np.ndarray) -> float:
        """The Bhattacharyya coefficient (0-1) of the colours of ``pixels`` (BGR uint8, (N, 3)) with the
        walker's model: which of the parts a merged blob splits into is the walker (module docstring)."""
        h = _histogram(colour_bins(pixels))
        return 0.0 if h is None or self.walker is None else float(np.sqrt(h * self.walker).sum())

    def _mean(self, old: np.ndarray | None, new: np.ndarray | None) -> np.ndarray | None:
        if new is None:
            return old
        return new if old is None else (1.0 - self.rate) * old + self.rate * new

    def see_others(self, patch: np.ndarray, mask: np.ndarray) -> None:
        """Learn the other people's colours: ``patch`` BGR uint8, ``mask`` bool, same size."""
        if mask.any():
            self.others = self._mean(self.others, _histogram(colour_bins(patch[mask])))

    def split(self, crop: np.ndarray, patch: np.ndarray, *, median_area: float = np.inf) -> np.ndarray:
        """The walker's blob ``crop`` (uint8 0/255) with the others' regions cut; learns the walker.

        ``patch`` is the frame (BGR uint8) under ``crop``; ``median_area`` the
        walker's median blob area over its last detections (inf while there are
        fewer than three: the track's first frames are learned whatever they
        hold). Pixels outside the blob count as no evidence. Returns ``crop``
        itself when nothing is cut.
        """
        inside = crop > 0
        area = int(np.count_nonzero(inside))
        cut = self.ready and self.others is not None
        learn = area <= STABLE * median_area
        if not area or not (cut or learn):
            return crop
        bins = colour_bins(patch)
        out = self._cut(crop, inside, bins) if cut else crop
        if learn:
            self.walker = self._mean(self.walker, _histogram(bins[inside]))
            self.learned += 1
        return out

    def _cut(self, crop: np.ndarray, inside: np.ndarray, bins: np.ndarray) -> np.ndarray:
        evidence = np.log((self.walker[bins] + _EPS) / (self.others[bins] + _EPS)).astype(np.float32)
        rows = np.flatnonzero(inside.any(axis=1))
        k = max(3, int(self.window * (rows[-1] - rows[0] + 1))) | 1
        weight = inside.astype(np.float32)
        mean = (cv2.blur(evidence * weight, (k, k), borderType=cv2.BORDER_CONSTANT)
                / np.maximum(cv2.blur(weight, (k, k), borderType=cv2.BORDER_CONSTANT), 1e-6))
        cut = _above_feet(inside & (mean < -np.log(self.ratio)), rows)
        if not cut.any():
            return crop
        out = crop.copy()
        out[cut] = 0
        if not out.any():
            return crop  # all of it the others' colours: not a merge this rule can split
        return large_components(out, PIECE, of_largest=True)


def _above_feet(cut: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """The regions of ``cut`` (bool) that reach above the blob's feet band, the lowest
    :data:`FEET` of the blob's rows ``rows`` (sorted indices of rows with blob pixels)."""
    if not cut.any():
        return cut
    _, labels, stats, _ = cv2.connectedComponentsWithStats(cut.view(np.uint8), connectivity=8)
    reaches = stats[:, cv2.CC_STAT_TOP] < rows[-1] + 1 - FEET * (rows[-1] - rows[0] + 1)
    reaches[0] = False  # the background label
    return reaches[labels]
