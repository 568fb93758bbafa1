"""``posecal model build|info``: the appearance model artifact (Izo–Grimson §4–5).

The default model lives in the cache directory (``$POSECAL_CACHE``, else
``$XDG_CACHE_HOME/posecal``, else ``~/.cache/posecal``) under a name that hashes its build settings and the
renderer version; any command that needs it builds it on first use
(:func:`get_default_model`), and ``posecal model build`` does so up front.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import CliError, CliFailure

__all__ = ["register", "cache_dir", "get_default_model", "default_model_path", "model_from_arg"]


def cache_dir() -> Path:
    """``$POSECAL_CACHE`` if set, else ``$XDG_CACHE_HOME/posecal``, else ``~/.cache/posecal`` (the XDG
    base directory specification; read at call time)."""
    from service.settings import xdg_dir

    return xdg_dir("POSECAL_CACHE", "XDG_CACHE_HOME", ".cache")


def _examples_key() -> dict:
    from estimator.appearance import _default_examples_key

    return _default_examples_key()


def default_model_path(*, n_clusters: int | None = None, seed: int = 0) -> Path:
    """Where :func:`get_default_model` keeps the model with these settings."""
    from estimator.appearance import DEFAULT_N_CLUSTERS, model_filename

    n = DEFAULT_N_CLUSTERS if n_clusters is None else n_clusters
    return cache_dir() / model_filename({**_examples_key(), "n_clusters": n, "seed": seed})


def get_default_model(*, progress: bool = False):
    """The default :class:`~estimator.appearance.AppearanceModel`, built and cached on first use."""
    from estimator.appearance import default_model

    with _Progress(enabled=progress) as bar:
        model = default_model(cache_dir(), make_examples=bar.render_examples, progress=bar.stage)
        bar.finish()
        return model


def model_from_arg(path: str | None):
    """The model a command's ``--model PATH`` names, else the default one (CliError if unreadable)."""
    if not path:
        return get_default_model(progress=True)
    from estimator.appearance import load_model

    try:
        return load_model(path)
    except (OSError, ValueError) as exc:
        raise CliError(f"cannot load model {path}: {exc}") from None


class _Progress:
    """tqdm bars: one for rendering (driven by the renderer's (done, total) callback),
    one for the build stages."""

    _STAGES = ("register", "em", "means")

    def __init__(self, *, enabled: bool = True) -> None:
        self.enabled = enabled
        self._render_bar = None
        self._stage_bar = None

    def __enter__(self) -> "_Progress":
        return self

    def __exit__(self, *exc) -> None:
        for bar in (self._render_bar, self._stage_bar):
            if bar is not None:
                bar.close()

    def _render_progress(self, done: int, total: int) -> None:
        if not self.enabled:
            return
        from tqdm import tqdm

        if self._render_bar is None:
            self._render_bar = tqdm(total=total, desc="render examples", unit="ex", file=sys.stderr)
        self._render_bar.update(done - self._render_bar.n)

    def render_examples(self):
        from estimator import examples as ex

        if not hasattr(ex, "render_examples"):
            raise CliFailure("the example renderer (estimator.examples.render_examples) is not available")
        return ex.render_examples(progress=self._render_progress)

    def finish(self) -> None:
        if self._stage_bar is not None:
            self._stage_bar.update(len(self._STAGES) - self._stage_bar.n)

    def stage(self, name: str) -> None:
        if not self.enabled or name == "render":
            return
        from tqdm import tqdm

        if self._stage_bar is None:
            if self._render_bar is not None:
                self._render_bar.close()
            self._stage_bar = tqdm(total=len(self._STAGES), desc="build model", unit="stage",
                                   file=sys.stderr)
        if name in self._STAGES:
            self._stage_bar.set_postfix_str(name)
            self._stage_bar.update(self._STAGES.index(name) - self._stage_bar.n)


def _build(args: argparse.Namespace) -> int:
    from estimator.appearance import DEFAULT_N_CLUSTERS, build_model, model_filename, save_model

    n = args.clusters if args.clusters is not None else DEFAULT_N_CLUSTERS
    if n < 1:
        raise CliError(f"--clusters must be >= 1, got {n}")
    key = _examples_key()
    out = Path(args.out) if args.out else cache_dir() / model_filename(
        {**key, "n_clusters": n, "seed": args.seed})
    with _Progress(enabled=not args.quiet) as bar:
        examples = bar.render_examples()
        if len(examples) < n:
            raise CliError(f"--clusters {n} is more than the {len(examples)} examples")
        model = build_model(examples, n_clusters=n, rng=args.seed, provenance=key, progress=bar.stage)
        bar.finish()
    save_model(model, out)
    print(f"{out}  ({model.n_examples} examples, {model.n_clusters} clusters, "
          f"{out.stat().st_size / 1e6:.1f} MB)")
    return 0


def _info(args: argparse.Namespace) -> int:
    from estimator.appearance import load_model

    path = Path(args.model) if args.model else default_model_path(n_clusters=args.clusters)
    if not path.exists():
        raise CliError(f"no appearance model at {path}; `posecal model build` makes it "
                       "(commands that need it build it on first use)")
    try:
        model = load_model(path)
    except ValueError as exc:
        raise CliError(str(exc)) from exc
    info = {"path": str(path), "size_mb": round(path.stat().st_size / 1e6, 3), **model.info()}
    if args.json:
        print(json.dumps(info, indent=2, sort_keys=True))
        return 0
    p = info["params"]
    m = info["members_per_cluster"]
    lines = [
        f"path          {info['path']} ({info['size_mb']} MB, format v{info['format_version']})",
        f"examples      {info['examples']} ({info['styles']} body styles)",
        f"clusters      {info['clusters']} (members min/median/max {m['min']}/{m['median']:g}/{m['max']})",
        f"canvas        {p['size'][0]}x{p['size'][1]} px, height fraction {p['height_fraction']}, "
        f"rotate {p['rotate']}",
        f"EM            reg_covar {p['reg_covar']}, tol {p['tol']}, max_iter {p['max_iter']}, "
        f"seed {p['seed']}",
    ]
    em = info["provenance"].get("em")
    if em:
        lines.append(f"EM run        {em['n_iter']} iterations, converged {em['converged']}")
    other = {k: v for k, v in info["provenance"].items() if k not in ("em", "timings")}
    if other:
        short = ", ".join(f"{k} {v}" for k, v in sorted(other.items())
                          if k != "source" and isinstance(v, (str, int, float, type(None))))
        more = sum(isinstance(v, (dict, list)) for v in other.values())
        lines.append(f"examples from {other.get('source', '?')}"
                     + (f" ({short})" if short else "")
                     + (f"; {more} more settings in --json" if more else ""))
    print("\n".join(lines))
    return 0


def register(subparsers) -> None:
    """Add ``model build`` and ``model info`` to the ``posecal`` parser."""
    parser = subparsers.add_parser("model", help="build or describe the appearance model",
                                   description="Build or describe the appearance model (Izo–Grimson §4–5).")
    sub = parser.add_subparsers(dest="model_command", required=True, metavar="ACTION")

    b = sub.add_parser("build", help="render the examples and build the model (cached)")
    b.add_argument("--out", metavar="PATH", help="write here instead of the cache directory")
    b.add_argument("--clusters", type=int, metavar="N", help="number of clusters (default: 100)")
    b.add_argument("--seed", type=int, default=0, help="seed of the clustering (default: 0)")
    b.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    b.set_defaults(func=_build)

    i = sub.add_parser("info", help="print examples, clusters and build parameters")
    i.add_argument("--model", metavar="PATH", help="a model file (default: the cached default model)")
    i.add_argument("--clusters", type=int, metavar="N", help=argparse.SUPPRESS)
    i.add_argument("--json", action="store_true", help="machine-readable output")
    i.set_defaults(func=_info)
