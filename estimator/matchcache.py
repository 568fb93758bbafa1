"""Each silhouette registered and matched once, across the overlapping windows of a stream.

Live windows overlap (20 frames every 10: each frame is estimated twice), and
within a window the clean-up's shadow test scores the same uncut silhouettes
that are then matched. What depends on a silhouette alone — its registration
(Izo–Grimson §5), its eq. 8 distance to every cluster mean and its walker
score (:func:`estimator.pipeline.walker_score`) — is kept here, keyed by the
silhouette's pixels, so that the window-level steps (viewpoint vote, phase
evidence, HMM) are all that a frame costs the second time.

A :class:`MatchCache` is an explicit argument, never a global: the results
are the same with or without one (``tests/test_pipeline.py``), up to the
float32 rounding of eq. 8's matrix product, which depends on the batch it is
computed in (a few 1e-4 pixels: it can only decide an exact tie). It is bound to
one appearance model (given another, it starts again) and bounded: the least
recently used silhouettes go first.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from .appearance import AppearanceModel
from .registration import distance

__all__ = ["MatchCache", "Matched", "match"]


@dataclass
class Matched:
    """Silhouettes registered with a model's canvas and matched with its cluster means.

    Attributes
    ----------
    registered : ndarray of shape (N, h, w), float32
        0/1 registered silhouettes (zeros where not ``valid``).
    valid : ndarray of shape (N,), bool
        Registered (not empty).
    means_distance : ndarray of shape (N, K), float32
        Eq. 8 distance to each cluster mean (inf where not ``valid``).
    score : ndarray of shape (N,)
        Walker score where the cache already holds it, else NaN.
    keys : list of bytes or None
        The silhouettes' cache keys (None without a cache).
    """

    registered: np.ndarray
    valid: np.ndarray
    means_distance: np.ndarray
    score: np.ndarray
    keys: list[bytes] | None = None


@dataclass
class _Entry:
    bits: np.ndarray  # the registered silhouette, packed
    valid: bool
    means_distance: np.ndarray
    score: float = np.nan


class MatchCache:
    """Registrations, distances to the means and walker scores of recently seen silhouettes.

    Parameters
    ----------
    max_entries : int
        Silhouettes kept (about 800 bytes each on the default 64 x 48 canvas
        with 100 clusters).
    """

    def __init__(self, max_entries: int = 4096) -> None:
        if max_entries < 1:
            raise ValueError(f"max_entries must be >= 1, got {max_entries}")
        self.max_entries = max_entries
        self._model: AppearanceModel | None = None
        self._entries: OrderedDict[bytes, _Entry] = OrderedDict()
        self.hits = self.misses = 0

    def __len__(self) -> int:
        return len(self._entries)

    @staticmethod
    def key(silhouette: np.ndarray) -> bytes:
        """The silhouette's identity: its shape and foreground pixels (0/1 or 0/255 alike)."""
        mask = np.asarray(silhouette) != 0
        h = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16)
        h.update(np.asarray(mask.shape, np.int64).tobytes())
        return h.digest()

    def _lookup(self, model: AppearanceModel, keys: Sequence[bytes]) -> list[_Entry | None]:
        if self._model is not model:  # bound to one model
            self._model, self._entries = model, OrderedDict()
        found = []
        for k in keys:
            entry = self._entries.get(k)
            if entry is not None:
                self._entries.move_to_end(k)
            found.append(entry)
        n_hit = sum(e is not None for e in found)
        self.hits += n_hit
        self.misses += len(found) - n_hit
        return found

    def _store(self, key: bytes, entry: _Entry) -> None:
        self._entries[key] = entry
        while len(self._entries) > self.max_entries:
            self._entries.popitem(last=False)

    def remember_scores(self, keys: Sequence[bytes], scores: np.ndarray) -> None:
        """Keep walker scores of silhouettes :func:`match` has seen (still held)."""
        for k, v in zip(keys, scores):
            entry = self._entries.get(k)
            if entry is not None:
                entry.score = float(v)


def _match_fresh(model: AppearanceModel, silhouettes: Sequence[np.ndarray]) -> Matched:
    registered, tf = model.register(list(silhouettes))
    dist = np.full((len(registered), model.n_clusters), np.inf, np.float32)
    if tf.valid.any():
        dist[tf.valid] = distance(registered[tf.valid], model.means)
    return Matched(registered, tf.valid.copy(), dist, np.full(len(registered), np.nan))


def match(model: AppearanceModel, silhouettes: Sequence[np.ndarray], cache: MatchCache | None = None) -> Matched:
    """Register ``silhouettes`` with ``model`` and take their eq. 8 distances to its means,
    reusing what ``cache`` holds (and filling it)."""
    if cache is None or not len(silhouettes):
        return _match_fresh(model, silhouettes)
    keys = [MatchCache.key(s) for s in silhouettes]
    entries = cache._lookup(model, keys)
    todo = [i for i, e in enumerate(entries) if e is None]
    if todo:
        fresh = _match_fresh(model, [silhouettes[i] for i in todo])
        for j, i in enumerate(todo):
            entries[i] = _Entry(np.packbits(fresh.registered[j] != 0), bool(fresh.valid[j]), fresh.means_distance[j])
            cache._store(keys[i], entries[i])
    h, w = model.params.size
    registered = np.unpackbits(np.stack([e.bits for e in entries]), axis=1, count=h * w)
    return Matched(registered.reshape(len(entries), h, w).astype(np.float32), np.array([e.valid for e in entries]),
                   np.stack([e.means_distance for e in entries]), np.array([e.score for e in entries], float), keys)
