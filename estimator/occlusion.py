"""A walker hidden below: matching what is visible of the body.

A low wall, a bench or a parked car in front of the walker, or the image's
bottom edge, hides the lowest part of the body. Izo–Grimson §5 registers a
silhouette by its centroid, principal axis and height, so such a walker is
placed and scaled as a whole, shorter body and matched with the wrong
examples (docs/ROBUSTNESS.md, "A walker hidden below").

Here the comparison is restricted to what both sides show. The examples
stay as they were registered (whole bodies, their tops about one canvas
row); the canvas is cut at the row that a body's ``1 - fraction`` of its
height reaches from there, and the examples' means and exemplars lose the
rows below it. The input is registered with its visible extent scaled to
that share of the target height and its top on the examples' top row
(:func:`estimator.registration.register`, ``hidden``), and loses the same
rows. The hidden share itself is searched per window
(:func:`hidden_fraction`): the one at whose scale the head and trunk fit
the examples best; 0 if a whole body does. Behind an edge fixed in the
image (a real wall: :func:`estimator.cleanup.fixed_edge`) each frame hides
its own share, which the walker's growth tells (:func:`hidden_shares`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from .cleanup import evenly_spaced
from .registration import register_shares

if TYPE_CHECKING:
    from .appearance import AppearanceModel

__all__ = ["HiddenBelow", "hidden_below", "hidden_fraction", "hidden_shares", "whole_height"]


def whole_height(visible: np.ndarray | float, share: np.ndarray | float) -> np.ndarray | float:
    """The walker's whole image height from the visible part's, its lowest ``share`` hidden below."""
    return visible / (1.0 - share)


def hidden_shares(visible: np.ndarray, growth: float, share: float, *, whole: np.ndarray | None = None,
                  most: float = 0.9) -> np.ndarray:
    """Each frame's hidden share behind an edge fixed in the image (:func:`estimator.cleanup.fixed_edge`).

    The visible heights ``visible`` (T,) (NaN where none) behind the edge are
    the edge's row less the walker's top, which tells nothing of the walker's
    size; the whole height grows by ``growth`` per frame (log scale:
    :func:`estimator.viewpoint.motion_cue`), ``exp(c + growth t)``. Frames
    ``whole`` (T,) bool passed the edge's end and show the walker whole: with
    3 of them or more, ``c`` makes their heights the whole ones (median), and
    they hide 0; else ``c`` makes the median frame behind the edge hide
    ``share`` (the window's, from :func:`hidden_fraction`). Shares are clipped
    to ``[0, most]``; NaN stays NaN.
    """
    h = np.asarray(visible, float)
    t = np.arange(h.size, dtype=float)
    whole = np.zeros(h.size, bool) if whole is None else np.asarray(whole, bool)
    ok = np.isfinite(h) & (h > 0)
    if not ok.any():
        return np.full(h.shape, np.nan)
    if np.sum(ok & whole) >= 3:
        c = np.median(np.log(h[ok & whole]) - growth * t[ok & whole])
    else:
        behind = ok & ~whole if (ok & ~whole).any() else ok
        c = np.log(np.median(h[behind] * np.exp(-growth * t[behind]))) - np.log1p(-share)
    out = np.clip(1.0 - h / np.exp(c + growth * t), 0.0, most)
    return np.where(whole & ok, 0.0, out)


@dataclass(frozen=True)
class HiddenBelow:
    """How an appearance model's canvas is cut for a walker hidden below.

    Attributes
    ----------
    fraction : float
        Share of the body's height hidden below the silhouettes.
    top : float
        Canvas row of a whole registered body's first row (the examples' median).
    rows : int
        Canvas rows compared: ``0:rows``; the rest is cleared in the examples and inputs alike.
    """

    fraction: float
    top: float
    rows: int


def hidden_below(model: AppearanceModel, fraction: float, *, compared: float | None = None,
                 cuts: dict[int, tuple[np.ndarray, np.ndarray]] | None = None) -> AppearanceModel:
    """``model`` (an :class:`~estimator.appearance.AppearanceModel`) for a walker whose lowest
    ``fraction`` of the height is hidden: its cluster means and exemplars cut below the rows such
    a walker shows, and its registration placing the visible part as those rows (module docstring).
    With ``compared``, the rows cut are those below the body's ``1 - compared`` instead
    (:func:`hidden_fraction` compares every fraction on the same rows).

    ``cuts`` maps a row count to the means and packed exemplars cut there, shared (read-only)
    by every cut model of that row count and filled here: the fractions searched on the same
    rows differ only in their registration. Prefer :meth:`AppearanceModel.hidden_below`, which
    builds each model once and keeps the cuts.
    """
    compared = fraction if compared is None else compared
    if not (0.0 <= fraction < 1.0 and 0.0 <= compared < 1.0):
        raise ValueError(f"fraction and compared must be in [0, 1), got {fraction}, {compared}")
    if model.hidden is not None:
        raise ValueError("the model is already cut for a hidden walker")
    h, w = model.size
    n = model.n_examples
    # Rows of whole bytes when the width is a multiple of 8 (the default canvas): no unpacking.
    bits = (model.member_bits.reshape(n, h, w // 8) if w % 8 == 0
            else np.unpackbits(model.member_bits, axis=1, count=h * w).reshape(n, h, w))
    top = float(np.median(bits.any(axis=2).argmax(axis=1)))
    rows = int(round(top + model.params.height_fraction * h * (1.0 - compared)))
    cuts = {} if cuts is None else cuts
    if rows not in cuts:
        bits = bits.copy()
        bits[:, rows:] = 0
        means = model.means.copy()
        means[:, rows:] = 0.0
        cuts[rows] = means, bits.reshape(n, -1) if w % 8 == 0 else np.packbits(bits.reshape(n, -1), axis=1)
    means, packed = cuts[rows]
    return replace(model, means=means, member_bits=packed, hidden=HiddenBelow(float(fraction), top, rows))


def hidden_fraction(model: AppearanceModel, silhouettes: Sequence[np.ndarray | None], fractions: Sequence[float],
                    score: Callable[[AppearanceModel, np.ndarray, np.ndarray], np.ndarray], *, frames: int = 8,
                    compared: float = 0.4) -> tuple[float, np.ndarray]:
    """The share of the body hidden below ``silhouettes`` (one camera's window, visible parts): the
    one of ``fractions`` at which they fit the examples best.

    Each fraction registers the silhouettes at its scale (their visible
    extent is ``1 - fraction`` of a body's), and all are compared on the same
    rows, the body's top ``1 - compared``: head and trunk, whose size then
    tells the scale; a fraction above ``compared`` leaves some of those rows
    empty and pays for it. Comparing each fraction on all the rows it shows
    favours the largest (the legs, the hardest part to fit, drop out), and so
    does a larger ``compared`` (real walkers are wider than the examples and
    fit better shrunk): both measured on vtest.avi's walkers cut by the
    image's bottom edge (docs/ROBUSTNESS.md). ``score(model, registered,
    valid)`` gives each registered silhouette's distance to the nearest
    example (:func:`estimator.pipeline.registered_walker_score`): the models
    cut at each fraction share their rows, means and examples and differ only
    in registration, so every silhouette is measured once and registered at
    every fraction (:func:`estimator.registration.register_shares`), and all
    are scored in one call. Up to ``frames`` silhouettes, evenly spaced, are
    scored. Returns the fraction and the mean score of each.
    """
    sils = [s for s in silhouettes if s is not None]
    if not sils or not len(fractions):
        raise ValueError("hidden_fraction needs silhouettes and fractions")
    sils = [sils[i] for i in evenly_spaced(len(sils), frames)]
    cut = [model.hidden_below(float(f), compared=compared) for f in fractions]
    first = cut[0]
    if any(m.hidden.rows != first.hidden.rows or m.means is not first.means for m in cut):
        raise ValueError("the cut models of one search must share their rows")  # compared is one for all
    p = first.params
    registered, valid = register_shares(sils, [m.hidden.fraction for m in cut], top=first.hidden.top, size=p.size,
                                        height_fraction=p.height_fraction, rotate=p.rotate)
    registered[:, :, first.hidden.rows:] = 0.0  # as AppearanceModel.register clears them
    d = np.asarray(score(first, registered.reshape(-1, *registered.shape[2:]), np.tile(valid, len(cut))), float)
    d = d.reshape(len(cut), len(sils))
    finite = np.isfinite(d)
    n = finite.sum(axis=1)
    costs = np.full(len(cut), np.inf)
    costs[n > 0] = np.where(finite, d, 0.0)[n > 0].sum(axis=1) / n[n > 0]  # the mean of the scored
    return float(fractions[int(np.argmin(costs))]), costs
