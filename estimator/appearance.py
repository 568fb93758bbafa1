"""Appearance model of walking (Izo–Grimson §4–5): clusters of rendered examples.

:func:`build_model` takes rendered :class:`~estimator.examples.Examples`, registers
their silhouettes (:mod:`estimator.registration`), clusters their registered 2D
joint vectors with a full-covariance Gaussian mixture fitted by EM (§4.1, eqs.
2–5), and averages each cluster's registered silhouettes into a mean silhouette
(§5). An :class:`AppearanceModel` matches new silhouettes against those means
with eq. 8 and keeps, per cluster, its members' (phase, azimuth, elevation) for
the camera-pose and phase steps that follow (§3 steps 4–5).
"""

from __future__ import annotations

import fcntl
import hashlib
import io
import json
import os
import tempfile
import time
import zipfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ._cluster import fit_gmm, within_scatter
from .examples import Examples
from .exemplars import ExemplarIndex, pack
from .joints import N_JOINTS
from .occlusion import HiddenBelow, hidden_below
from .registration import DEFAULT_SIZE, Transforms, _distance_flat, register, transform_points

__all__ = [
    "FORMAT_VERSION",
    "DEFAULT_N_CLUSTERS",
    "BuildParams",
    "AppearanceModel",
    "build_model",
    "joint_features",
    "within_scatter_curve",
    "choose_n_clusters",
    "save_model",
    "load_model",
    "default_model",
    "model_filename",
]

FORMAT_VERSION = 2
"""Version of the artifact layout written by :func:`save_model` (2: with ``member_bits``)."""

DEFAULT_N_CLUSTERS = 100
"""Number of clusters (the paper's N; see docs/APPEARANCE.md for the within-scatter curve)."""


@dataclass(frozen=True)
class BuildParams:
    """Parameters of :func:`build_model`, stored in the artifact.

    Attributes
    ----------
    n_clusters : int
        Number of Gaussian components N (eq. 2). Components that end up with no
        member under the argmax assignment are dropped.
    size : (int, int)
        Registered canvas (height, width) in pixels.
    height_fraction : float
        Fraction of the canvas height that a registered silhouette fills.
    rotate : bool
        Align principal axes during registration.
    reg_covar : float
        Added to the diagonal of each covariance (feature units: body heights,
        so 1e-4 is a 1 % standard deviation floor); keeps eq. 5 invertible for
        clusters whose members lie on a low-dimensional manifold.
    tol : float
        EM stops when ``sum_j ||mu_j^t - mu_j^(t-1)|| < tol`` (§4.1 step 3),
        in body heights. The default 0.05 is, for N = 100, a mean shift of 5e-4
        body heights (0.03 canvas pixels) per cluster.
    max_iter : int
        Cap on EM iterations.
    seed : int or None
        Seed of the k-means initialisation (None if a Generator was passed).
    """

    n_clusters: int = DEFAULT_N_CLUSTERS
    size: tuple[int, int] = DEFAULT_SIZE
    height_fraction: float = 0.8
    rotate: bool = True
    reg_covar: float = 1e-4
    tol: float = 0.05
    max_iter: int = 200
    seed: int | None = 0

    def __post_init__(self) -> None:
        if self.n_clusters < 1:
            raise ValueError(f"n_clusters must be >= 1, got {self.n_clusters}")
        if self.max_iter < 0:
            raise ValueError(f"max_iter must be >= 0, got {self.max_iter}")
        object.__setattr__(self, "size", (int(self.size[0]), int(self.size[1])))


@dataclass(frozen=True, eq=False)
class AppearanceModel:
    """Clusters of rendered examples with their mean silhouettes (§4–5).

    Attributes
    ----------
    means : ndarray of shape (K, h, w), float32
        Mean registered silhouette of each cluster: per-pixel probability that a
        member is foreground (§5).
    gmm_weights : ndarray of shape (K,)
        Priors P(j) of eq. 2 (renormalised over the kept components).
    gmm_means : ndarray of shape (K, 26)
        Means mu_j of eq. 2, registered joint vectors ``(u0, v0, u1, ...)`` in
        body heights relative to the canvas centre.
    gmm_covariances : ndarray of shape (K, 26, 26)
        Covariances Sigma_j of eq. 2.
    member_offsets : ndarray of shape (K + 1,), int64
        Members of cluster k are rows ``member_offsets[k]:member_offsets[k + 1]``
        of the ``member_*`` arrays.
    member_index : ndarray of shape (N,), int64
        Index of each member in the examples the model was built from.
    member_phase, member_azimuth_deg, member_elevation_deg : ndarray of shape (N,)
        Each member's walking phase and camera viewpoint (DESIGN.md conventions).
    member_style : ndarray of shape (N,), int
        Body style each member was rendered with.
    member_bits : ndarray of shape (N, ceil(h * w / 8)), uint8
        Each member's registered binary silhouette, bit-packed
        (:func:`estimator.exemplars.pack`): the exemplars the estimator compares
        inputs with beyond the cluster means.
    params : BuildParams
        How the model was built.
    hidden : HiddenBelow or None
        Set on a model cut for a walker hidden below (:meth:`hidden_below`, not
        saved); its ``gmm_*`` stay the whole body's.
    provenance : dict
        JSON-able description of the examples (renderer, body/gait version, ...).
    version : int
        Artifact format version.
    """

    means: np.ndarray
    gmm_weights: np.ndarray
    gmm_means: np.ndarray
    gmm_covariances: np.ndarray
    member_offsets: np.ndarray
    member_index: np.ndarray
    member_phase: np.ndarray
    member_azimuth_deg: np.ndarray
    member_elevation_deg: np.ndarray
    member_style: np.ndarray
    member_bits: np.ndarray
    params: BuildParams = field(default_factory=BuildParams)
    provenance: dict = field(default_factory=dict)
    version: int = FORMAT_VERSION
    hidden: HiddenBelow | None = None

    def __post_init__(self) -> None:
        k = len(self.means)
        if self.means.ndim != 3 or tuple(self.means.shape[1:]) != tuple(self.params.size):
            raise ValueError(f"means must have shape (K, {self.params.size}), got {self.means.shape}")
        d = 2 * N_JOINTS
        if self.gmm_means.shape != (k, d) or self.gmm_covariances.shape != (k, d, d):
            raise ValueError(f"GMM parameters must have shapes ({k}, {d}) and ({k}, {d}, {d})")
        if self.member_offsets.shape != (k + 1,) or self.member_offsets[-1] != len(self.member_index):
            raise ValueError("member_offsets must have shape (K + 1,) and end at the member count")
        n_bits = (self.means.shape[1] * self.means.shape[2] + 7) // 8
        if self.member_bits.shape != (len(self.member_index), n_bits) or self.member_bits.dtype != np.uint8:
            raise ValueError(f"member_bits must be a ({len(self.member_index)}, {n_bits}) uint8 array")
        # Flattened float32 means for eq. 8, computed once.
        flat = np.ascontiguousarray(self.means, dtype=np.float32).reshape(k, -1)
        object.__setattr__(self, "_flat", flat)
        object.__setattr__(self, "_sum", flat.sum(1))

    # -- sizes -------------------------------------------------------------------
    @property
    def n_clusters(self) -> int:
        return len(self.means)

    @property
    def n_examples(self) -> int:
        return len(self.member_index)

    @property
    def size(self) -> tuple[int, int]:
        return self.params.size

    @property
    def labels(self) -> np.ndarray:
        """Cluster of each example, in the examples' order: ndarray of shape (N,)."""
        out = np.empty(self.n_examples, np.int64)
        out[self.member_index] = np.repeat(np.arange(self.n_clusters), np.diff(self.member_offsets))
        return out

    def members(self, k: int) -> dict[str, np.ndarray]:
        """Members of cluster ``k``: arrays ``index, phase, azimuth_deg, elevation_deg, style``."""
        if not 0 <= k < self.n_clusters:
            raise ValueError(f"cluster index must be in [0, {self.n_clusters}), got {k}")
        sl = slice(self.member_offsets[k], self.member_offsets[k + 1])
        return {
            "index": self.member_index[sl],
            "phase": self.member_phase[sl],
            "azimuth_deg": self.member_azimuth_deg[sl],
            "elevation_deg": self.member_elevation_deg[sl],
            "style": self.member_style[sl],
        }

    def exemplars(self) -> ExemplarIndex:
        """The members' packed silhouettes with their phase and viewpoint (built once)."""
        index = self.__dict__.get("_exemplars")
        if index is None:
            index = ExemplarIndex(
                bits=self.member_bits,
                phase=self.member_phase,
                azimuth_deg=self.member_azimuth_deg,
                elevation_deg=self.member_elevation_deg,
                style=self.member_style,
            )
            object.__setattr__(self, "_exemplars", index)
        return index

    # -- per-cluster summaries (§3 steps 4–5) --------------------------------------
    def _circular_mean(self, values: np.ndarray, period: float) -> np.ndarray:
        ang = values * (2 * np.pi / period)
        k = np.repeat(np.arange(self.n_clusters), np.diff(self.member_offsets))
        c = np.bincount(k, np.cos(ang), self.n_clusters)
        s = np.bincount(k, np.sin(ang), self.n_clusters)
        return (np.arctan2(s, c) * (period / (2 * np.pi))) % period

    @property
    def cluster_phase(self) -> np.ndarray:
        """Circular mean phase of each cluster's members, in [0, 1): shape (K,)."""
        return self._circular_mean(self.member_phase, 1.0)

    @property
    def cluster_viewpoint(self) -> np.ndarray:
        """Mean (azimuth_deg, elevation_deg) of each cluster's members (azimuth circular): (K, 2)."""
        counts = np.diff(self.member_offsets)
        k = np.repeat(np.arange(self.n_clusters), counts)
        el = np.bincount(k, self.member_elevation_deg, self.n_clusters) / np.maximum(counts, 1)
        return np.stack([self._circular_mean(self.member_azimuth_deg, 360.0), el], -1)

    # -- matching (§5) --------------------------------------------------------------
    def register(self, silhouettes) -> tuple[np.ndarray, Transforms]:
        """Register silhouettes with this model's canvas and settings (see :func:`register`; a model
        cut for a walker hidden below registers the visible part as such and clears the same rows)."""
        p = self.params
        if self.hidden is None:
            return register(silhouettes, size=p.size, height_fraction=p.height_fraction, rotate=p.rotate)
        reg, tf = register(silhouettes, size=p.size, height_fraction=p.height_fraction, rotate=p.rotate,
                           hidden=self.hidden.fraction, top=self.hidden.top)
        reg[:, self.hidden.rows:] = 0.0
        return reg, tf

    def hidden_below(self, fraction: float, *, compared: float | None = None) -> AppearanceModel:
        """This model for a walker whose lowest ``fraction`` of the height is hidden (a low wall, the
        image's bottom edge): :func:`estimator.occlusion.hidden_below`, built once per fraction."""
        made = self.__dict__.setdefault("_hidden_below", {})
        key = (round(float(fraction), 4), None if compared is None else round(float(compared), 4))
        if key not in made:
            made[key] = hidden_below(self, key[0], compared=key[1], cuts=self.__dict__.setdefault("_cuts", {}))
        return made[key]

    def distances(self, silhouettes) -> np.ndarray:
        """Eq. 8 distance from each silhouette to each cluster mean.

        Parameters
        ----------
        silhouettes : ndarray of shape (T, H, W), or sequence of 2-D arrays
            Binary input silhouettes (non-zero = foreground), unregistered.

        Returns
        -------
        ndarray of shape (T, K), float32
            Empty silhouettes get ``inf`` in every column.
        """
        reg, tf = self.register(silhouettes)
        d = _distance_flat(reg.reshape(len(reg), -1), self._flat, self._sum)
        d[~tf.valid] = np.inf
        return d

    def match(self, silhouettes) -> tuple[np.ndarray, np.ndarray]:
        """Best cluster per silhouette (§3 step 3).

        Returns
        -------
        best : ndarray of shape (T,), int64
            Index of the cluster with the smallest eq. 8 distance (-1 for empty inputs).
        distances : ndarray of shape (T, K), float32
        """
        d = self.distances(silhouettes)
        best = d.argmin(1) if d.size else np.zeros(len(d), np.int64)
        best[~np.isfinite(d).any(1)] = -1
        return best, d

    def info(self) -> dict:
        """JSON-able summary: examples, clusters, parameters, provenance."""
        counts = np.diff(self.member_offsets)
        return {
            "format_version": self.version,
            "examples": self.n_examples,
            "clusters": self.n_clusters,
            "members_per_cluster": {
                "min": int(counts.min()), "median": float(np.median(counts)), "max": int(counts.max())
            },
            "styles": int(len(np.unique(self.member_style))),
            "params": asdict(self.params),
            "provenance": self.provenance,
        }


# -- building -------------------------------------------------------------------------


def joint_features(
    joints2d: np.ndarray, transforms: Transforms, *, size: tuple[int, int], height_fraction: float
) -> np.ndarray:
    """Registered joint vectors x_i of §4.1.

    Parameters
    ----------
    joints2d : ndarray of shape (N, 13, 2)
        Joints in the silhouettes' pixel coordinates.
    transforms : Transforms
        From registering those silhouettes.

    Returns
    -------
    ndarray of shape (N, 26)
        Joints mapped by the silhouette's registration (common height, centroid,
        principal axis), relative to the canvas centre, in units of the registered
        body height: ``(u0, v0, u1, v1, ...)``.
    """
    h, w = size
    pts = transform_points(transforms, joints2d)
    pts -= np.array([(w - 1) / 2.0, (h - 1) / 2.0])
    pts /= height_fraction * h
    return pts.reshape(len(pts), -1)


def _as_seed(rng) -> tuple[np.random.Generator, int | None]:
    if isinstance(rng, np.random.Generator):
        return rng, None
    if rng is None or isinstance(rng, (int, np.integer)):
        seed = None if rng is None else int(rng)
        return np.random.default_rng(seed), seed
    raise ValueError(f"rng must be an int, None or a numpy.random.Generator, got {type(rng).__name__}")


def build_model(
    examples: Examples,
    *,
    n_clusters: int = DEFAULT_N_CLUSTERS,
    rng: np.random.Generator | int | None = 0,
    size: tuple[int, int] = DEFAULT_SIZE,
    height_fraction: float = 0.8,
    reg_covar: float = 1e-4,
    tol: float = 0.05,
    max_iter: int = 200,
    provenance: dict | None = None,
    progress: Callable[[str], None] | None = None,
) -> AppearanceModel:
    """Build the appearance model from rendered examples (§4.1, §5).

    Parameters
    ----------
    examples : Examples
        N rendered examples (silhouettes, joints, phase, viewpoint, style).
    n_clusters : int, keyword-only
        Number of Gaussian components N.
    rng : {numpy.random.Generator, int, None}, keyword-only
        Seeds the k-means initialisation. Same seed and examples, same model.
    size, height_fraction : keyword-only
        Registration canvas (see :func:`~estimator.registration.register`).
    reg_covar, tol, max_iter : keyword-only
        EM settings (see :class:`BuildParams`).
    provenance : dict, keyword-only
        JSON-able description of the examples (renderer and body/gait version,
        rendering parameters), stored in the artifact.
    progress : callable, keyword-only
        Called with the name of each stage as it starts.

    Returns
    -------
    AppearanceModel

    Notes
    -----
    1. Register every silhouette; map its 13 joints with the same similarity
       (:func:`joint_features`), giving x_i in R^26.
    2. Fit eq. 2 by EM (eqs. 3–5) from a k-means start (§4.1) until the summed
       mean shift is below ``tol``; label each example by its most responsible
       component (so every example belongs to exactly one cluster).
    3. Mean silhouette of each cluster: per-pixel mean of its members' registered
       silhouettes (§5).
    """
    if not isinstance(examples, Examples):
        raise ValueError(f"examples must be an estimator.examples.Examples, got {type(examples).__name__}")
    n = len(examples)
    if n < n_clusters:
        raise ValueError(f"need at least n_clusters={n_clusters} examples, got {n}")
    gen, seed = _as_seed(rng)
    params = BuildParams(
        n_clusters=n_clusters, size=size, height_fraction=height_fraction,
        reg_covar=reg_covar, tol=tol, max_iter=max_iter, seed=seed,
    )
    note = progress or (lambda stage: None)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    note("register")
    reg, tf = register(examples.silhouettes, size=params.size, height_fraction=height_fraction,
                       rotate=params.rotate)
    if not tf.valid.all():
        bad = np.flatnonzero(~tf.valid)[:5].tolist()
        raise ValueError(f"examples contain empty silhouettes (e.g. indices {bad})")
    x = joint_features(examples.joints2d, tf, size=params.size, height_fraction=height_fraction)
    t1 = time.perf_counter()
    timings["register_s"] = t1 - t0

    note("em")
    fit = fit_gmm(x, n_clusters, rng=gen, tol=tol, max_iter=max_iter, reg_covar=reg_covar)
    t2 = time.perf_counter()
    timings["em_s"] = t2 - t1

    note("means")
    kept = np.flatnonzero(np.bincount(fit.labels, minlength=n_clusters) > 0)
    remap = np.full(n_clusters, -1)
    remap[kept] = np.arange(len(kept))
    labels = remap[fit.labels]
    order = np.argsort(labels, kind="stable")
    counts = np.bincount(labels, minlength=len(kept))
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    flat = reg.reshape(n, -1)
    means = np.empty((len(kept), flat.shape[1]), np.float32)
    for k in range(len(kept)):  # loop over clusters, not examples
        means[k] = flat[order[offsets[k] : offsets[k + 1]]].mean(0)
    timings["means_s"] = time.perf_counter() - t2
    weights = fit.weights[kept] / fit.weights[kept].sum()

    prov = dict(provenance or {})
    prov["em"] = {"n_iter": fit.n_iter, "converged": fit.converged,
                  "mean_log_likelihood": fit.mean_log_likelihood,
                  "dropped_components": int(n_clusters - len(kept))}
    prov["timings"] = {k: round(v, 3) for k, v in timings.items()}
    return AppearanceModel(
        means=means.reshape(len(kept), *params.size),
        gmm_weights=weights,
        gmm_means=fit.means[kept],
        gmm_covariances=fit.covariances[kept],
        member_offsets=offsets,
        member_index=order.astype(np.int64),
        member_phase=np.asarray(examples.phase, np.float64)[order],
        member_azimuth_deg=np.asarray(examples.azimuth_deg, np.float64)[order],
        member_elevation_deg=np.asarray(examples.elevation_deg, np.float64)[order],
        member_style=np.asarray(examples.style, np.int64)[order],
        member_bits=pack(reg)[order],
        params=params,
        provenance=prov,
    )


# -- number of clusters (§4.2) -----------------------------------------------------------


def within_scatter_curve(
    examples: Examples,
    ks,
    *,
    rng: np.random.Generator | int | None = 0,
    size: tuple[int, int] = DEFAULT_SIZE,
    height_fraction: float = 0.8,
    minibatch: bool = False,
) -> np.ndarray:
    """Trace of the within-scatter matrix (eqs. 6–7) of k-means partitions.

    Parameters
    ----------
    examples : Examples
    ks : sequence of int
        Numbers of clusters to try.
    rng : keyword-only
        Seeds the k-means runs.

    Returns
    -------
    ndarray of shape (len(ks),)
        ``tr[S_W] = sum_j sum_{x in C_j} ||x - mu_j||^2`` on the same joint vectors
        as :func:`build_model` (body heights squared).
    """
    ks = [int(k) for k in ks]
    if not ks or min(ks) < 1 or max(ks) > len(examples):
        raise ValueError(f"ks must be in [1, {len(examples)}], got {ks}")
    gen, _ = _as_seed(rng)
    _, tf = register(examples.silhouettes, size=size, height_fraction=height_fraction)
    x = joint_features(examples.joints2d, tf, size=size, height_fraction=height_fraction)
    return within_scatter(x, ks, rng=gen, minibatch=minibatch)


def choose_n_clusters(ks, trace) -> int:
    """The knee of a within-scatter curve.

    ``tr[S_W]`` is the k-means objective (eq. 7), which for optimal partitions
    never increases with k, so its minimum is the largest k tried; the paper's choice ("smallest for
    100") is the end of its sweep. This returns the point of the curve farthest
    below the chord joining its ends after scaling both axes to [0, 1]
    ("Kneedle", Satopää et al. 2011): beyond it, more clusters buy little
    tightness.
    """
    ks = np.asarray(ks, float)
    tr = np.asarray(trace, float)
    if ks.shape != tr.shape or len(ks) < 3:
        raise ValueError("ks and trace must be 1-D of the same length >= 3")
    x = (ks - ks.min()) / np.ptp(ks)
    y = (tr - tr.min()) / max(np.ptp(tr), 1e-300)
    return int(ks[np.argmax(1.0 - x - y)])


# -- artifact -------------------------------------------------------------------------


_ARRAYS = (
    "gmm_weights", "gmm_means", "gmm_covariances", "member_offsets", "member_index",
    "member_phase", "member_azimuth_deg", "member_elevation_deg", "member_style", "member_bits",
)


def save_model(model: AppearanceModel, path: str | os.PathLike) -> Path:
    """Write the model as one compressed ``.npz`` (means as float16), atomically.

    The file holds ``format_version``, a JSON ``meta`` (build parameters,
    provenance) and the arrays of :class:`AppearanceModel`.
    """
    if model.hidden is not None:
        raise ValueError("a model cut for a hidden walker is derived, not saved: save the whole one")
    path = Path(path)
    meta = {"format_version": model.version, "params": asdict(model.params),
            "provenance": model.provenance}
    arrays = {name: getattr(model, name) for name in _ARRAYS}
    arrays["means"] = model.means.astype(np.float16)
    arrays["format_version"] = np.array(model.version)
    arrays["meta"] = np.array(json.dumps(meta, sort_keys=True))
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(buf.getvalue())
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    return path


def load_model(path: str | os.PathLike) -> AppearanceModel:
    """Read a model written by :func:`save_model`.

    Raises
    ------
    ValueError
        If the file is not an appearance model or has another format version.
    """
    try:
        with np.load(path, allow_pickle=False) as z:
            if "format_version" not in z.files or "meta" not in z.files:
                raise ValueError(f"{path} is not a posecal appearance model")
            version = int(z["format_version"])
            if version != FORMAT_VERSION:
                raise ValueError(f"{path} has format version {version}, expected {FORMAT_VERSION}")
            meta = json.loads(str(z["meta"]))
            arrays = {name: z[name] for name in _ARRAYS}
            means = z["means"].astype(np.float32)
    except (OSError, KeyError, EOFError, zipfile.BadZipFile) as exc:  # truncated or foreign file
        raise ValueError(f"cannot read appearance model {path}: {exc}") from exc
    p = meta["params"]
    p["size"] = tuple(p["size"])
    return AppearanceModel(means=means, params=BuildParams(**p), provenance=meta["provenance"],
                           version=version, **arrays)


def model_filename(key: dict) -> str:
    """Cache file name for a model built with ``key`` (JSON-able build settings)."""
    blob = json.dumps({"format_version": FORMAT_VERSION, **key}, sort_keys=True).encode()
    return f"appearance-v{FORMAT_VERSION}-{hashlib.sha256(blob).hexdigest()[:12]}.npz"


def default_model(
    cache_dir: str | os.PathLike,
    *,
    make_examples: Callable[[], Examples] | None = None,
    key: dict | None = None,
    n_clusters: int = DEFAULT_N_CLUSTERS,
    rng: int = 0,
    progress: Callable[[str], None] | None = None,
) -> AppearanceModel:
    """Load the default model from ``cache_dir``, building and caching it on first use
    (under a file lock: processes that need it at once build it once).

    Parameters
    ----------
    cache_dir : path
        Directory of cached models (the service/CLI resolves ``$POSECAL_CACHE`` or
        ``~/.cache/posecal``; this function reads no environment).
    make_examples : callable, keyword-only
        Returns the examples to build from; defaults to
        ``estimator.examples.render_examples()`` with its default parameters.
    key : dict, keyword-only
        JSON-able description of the examples (renderer version, parameters): the
        cache file name is a hash of it and the build settings, and it is stored as
        the model's provenance.
    n_clusters, rng : keyword-only
        Build settings.
    progress : callable, keyword-only
        Stage names, as for :func:`build_model` (plus ``"render"``).
    """
    key = dict(key or _default_examples_key())
    name = model_filename({**key, "n_clusters": n_clusters, "seed": rng})
    path = Path(cache_dir) / name
    model = _load_cached(path)
    if model is not None:
        return model
    path.parent.mkdir(parents=True, exist_ok=True)
    # Processes that start together on a fresh machine (service replicas, test workers)
    # build the model once: the first holds the lock, the others load its file.
    with open(path.with_name(path.name + ".lock"), "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        model = _load_cached(path)
        if model is None:
            model = _build_default(path, key, make_examples, n_clusters, rng, progress)
    return model


def _load_cached(path: Path) -> AppearanceModel | None:
    """The model cached at ``path``; None if there is none or it is stale or truncated."""
    if not path.exists():
        return None
    try:
        return load_model(path)
    except ValueError:
        return None


def _build_default(path: Path, key: dict, make_examples: Callable[[], Examples] | None, n_clusters: int,
                   rng: int, progress: Callable[[str], None] | None) -> AppearanceModel:
    """Build the default model (:func:`default_model`) and save it at ``path``."""
    if progress:
        progress("render")
    if make_examples is None:
        from . import examples as _ex

        if not hasattr(_ex, "render_examples"):
            raise RuntimeError("estimator.examples.render_examples is not available to build the model")
        examples = _ex.render_examples()
    else:
        examples = make_examples()
    model = build_model(examples, n_clusters=n_clusters, rng=rng, provenance=key, progress=progress)
    save_model(model, path)
    return model


def _default_examples_key() -> dict:
    """Describe ``render_examples()``'s defaults: the cache key and provenance of the default model."""
    from . import examples as _ex
    from .gait import GAIT_VERSION, GaitStyle
    from .skeleton import BodyShape

    key: dict = {"source": "estimator.examples.render_examples", "gait_version": GAIT_VERSION,
                 "render_version": getattr(_ex, "RENDER_VERSION", None),
                 "body": asdict(BodyShape()), "gait_style": asdict(GaitStyle())}
    grid = getattr(_ex, "ExampleGrid", None)
    if grid is not None:
        key["grid"] = json.loads(json.dumps(asdict(grid())))
    return key
