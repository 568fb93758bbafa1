"""Each silhouette registered and matched once, across the overlapping windows of a stream.

Live windows overlap (20 frames every 10: each frame is estimated twice), and
within a window the clean-up's shadow test scores the same uncut silhouettes
that are then matched. What depends on a silhouette alone — its registration
(Izo–Grimson §5) and its eq. 8 distance to every cluster mean — is kept here,
keyed by the silhouette's pixels, and so is what depends on the silhouette and
a few window-level choices (:meth:`MatchCache.derived`, under a tag naming
them: the members of its nearest clusters, the examples at its decoded phase),
so that the viewpoint votes, the phase evidence at the window's viewpoint and
the HMM are most of what a frame costs the second time.

A :class:`MatchCache` is an explicit argument, never a global: the results
are the same with or without one (``tests/test_pipeline.py``), up to the
float32 rounding of eq. 8's matrix product, which depends on the batch it is
computed in (a few 1e-4 pixels: it can only decide an exact tie). It is bound to
one appearance model (given another, it starts again) and bounded: the least
recently used silhouettes go first. A camera whose walker is hidden below is
matched with a model cut for it (:meth:`AppearanceModel.hidden_below`), whose
registrations differ: :meth:`MatchCache.for_cut` keeps a smaller cache of its
own for each of the last few cut models.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from collections.abc import Callable, Hashable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .appearance import AppearanceModel
from .registration import distance

__all__ = ["MatchCache", "Matched", "derived", "match", "means_distance"]


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
    keys : list of bytes or None
        The silhouettes' cache keys (None without a cache).
    """

    registered: np.ndarray
    valid: np.ndarray
    means_distance: np.ndarray
    keys: list[bytes] | None = None


@dataclass
class _Entry:
    bits: np.ndarray  # the registered silhouette, packed
    valid: bool
    means_distance: np.ndarray
    derived: dict[Hashable, Any] = field(default_factory=dict)  # MatchCache.derived, by tag


class MatchCache:
    """Registrations, distances to the means and walker scores of recently seen silhouettes.

    Parameters
    ----------
    max_entries : int
        Silhouettes kept (about 800 bytes each on the default 64 x 48 canvas
        with 100 clusters, and ~10 kB of derived results per phase or view
        it was compared at).
    """

    max_cut_models = 4  # cut models with a cache of their own (for_cut), the least recently used dropped

    def __init__(self, max_entries: int = 4096) -> None:
        if max_entries < 1:
            raise ValueError(f"max_entries must be >= 1, got {max_entries}")
        self.max_entries = max_entries
        self._model: AppearanceModel | None = None
        self._entries: OrderedDict[bytes, _Entry] = OrderedDict()
        self._cut: list[tuple[AppearanceModel, MatchCache]] = []  # (cut model, its cache), oldest first
        self.hits = self.misses = 0  # silhouettes found / not found (registration and eq. 8)
        self.derived_hits = self.derived_misses = 0  # the same for derived results (MatchCache.derived)

    def __len__(self) -> int:
        return len(self._entries)

    @staticmethod
    def key(silhouette: np.ndarray) -> bytes:
        """The silhouette's identity: its shape and foreground pixels (0/1 or 0/255 alike)."""
        mask = np.asarray(silhouette) != 0
        h = hashlib.blake2b(np.packbits(mask).tobytes(), digest_size=16)
        h.update(np.asarray(mask.shape, np.int64).tobytes())
        return h.digest()

    def for_cut(self, model: AppearanceModel) -> MatchCache:
        """The cache of ``model``, a model cut for a walker hidden below (the same object for each
        share, :meth:`AppearanceModel.hidden_below`): a quarter of this one's size, one for each of
        the last :attr:`max_cut_models` cut models asked for. Its keys and derived results are its
        own: a camera matched with the cut model is cached there, never here."""
        if model.hidden is None:
            raise ValueError("for_cut takes a model cut for a walker hidden below")
        for i, (cut, cache) in enumerate(self._cut):
            if cut is model:
                self._cut.append(self._cut.pop(i))
                return cache
        cache = MatchCache(max(1, self.max_entries // 4))
        self._cut = [*self._cut, (model, cache)][-self.max_cut_models:]
        return cache

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

    def derived(self, keys: Sequence[bytes], tag: Hashable | Sequence[Hashable],
                compute: Callable[[np.ndarray], Sequence[Any]]) -> list[Any]:
        """Per silhouette (``keys``), what ``compute`` gives for it under ``tag`` (one for all, or a
        list of one per silhouette): anything that depends on the silhouette alone once the tag's
        choices are made. ``compute`` is called once, with the positions in ``keys`` of the
        silhouettes not holding it yet, and returns one value each; a silhouette no longer held
        is computed and not kept."""
        tags = tag if isinstance(tag, list) else [tag] * len(keys)
        entries = [self._entries.get(k) for k in keys]
        out = [None if e is None else e.derived.get(t) for e, t in zip(entries, tags)]
        todo = np.array([i for i, v in enumerate(out) if v is None], int)
        self.derived_hits += len(out) - todo.size
        self.derived_misses += todo.size
        if todo.size:
            for i, v in zip(todo, compute(todo)):
                out[i] = v
                if entries[i] is not None:
                    entries[i].derived[tags[i]] = v
        return out


def derived(cache: MatchCache | None, keys: Sequence[bytes] | None, n: int, tag: Hashable | list[Hashable],
            compute: Callable[[np.ndarray], Sequence[Any]]) -> list[Any]:
    """:meth:`MatchCache.derived` for ``n`` silhouettes, or ``compute`` on all of them without a cache."""
    if cache is None or keys is None:
        return list(compute(np.arange(n)))
    return cache.derived(keys, tag, compute)


def means_distance(model: AppearanceModel, registered: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Eq. 8 distance of each registered silhouette to each of ``model``'s cluster means, (N, K)
    float32; inf where not ``valid``."""
    dist = np.full((len(registered), model.n_clusters), np.inf, np.float32)
    if valid.any():
        dist[valid] = distance(registered[valid], model.means)
    return dist


def _match_fresh(model: AppearanceModel, silhouettes: Sequence[np.ndarray]) -> Matched:
    registered, tf = model.register(list(silhouettes))
    return Matched(registered, tf.valid.copy(), means_distance(model, registered, tf.valid))


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
                   np.stack([e.means_distance for e in entries]), keys)
