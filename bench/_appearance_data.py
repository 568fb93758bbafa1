"""Examples for the appearance benchmarks and evaluation.

``training_examples()`` is the 17,280-example grid of the paper (20 phases x 72
azimuths x 12 elevations): from ``estimator.examples.render_examples`` when it
exists, else rendered here with the project's body renderer (nominal body,
average gait), else the stick figures of ``estimator._stick_examples``.
``fresh_examples()`` draws new walkers for evaluation: random body shape and
gait style, off-grid phase and viewpoint, camera distance and focal length
(so silhouette sizes vary), rendered with the same renderer.

Rendered sets are cached as .npz under ``$POSECAL_CACHE/bench`` (or
``~/.cache/posecal/bench``) so that repeated benchmark runs do not re-render.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from estimator.examples import Examples  # noqa: E402

IMAGE_SIZE = (160, 320)  # (width, height), as bench/bench_render.py
ELEVATIONS = np.arange(-20.0, 36.0, 5.0)
AZIMUTHS = np.arange(0.0, 360.0, 5.0)
N_PHASES = 20


def cache_dir() -> Path:
    env = os.environ.get("POSECAL_CACHE")
    base = Path(env).expanduser() if env else Path.home() / ".cache" / "posecal"
    return base / "bench"


def _save(path: Path, ex: Examples) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, silhouettes=ex.silhouettes, joints2d=ex.joints2d, phase=ex.phase,
             azimuth_deg=ex.azimuth_deg, elevation_deg=ex.elevation_deg, style=ex.style)
    os.replace(tmp, path)


def _load(path: Path) -> Examples:
    with np.load(path) as z:
        return Examples(**{k: z[k] for k in z.files})


def _render(phases, azimuths, elevations, shapes, styles, distances, focals, *, progress=None):
    """Render one example per row of the argument arrays with the body renderer."""
    from estimator.camera import Camera
    from estimator.gait import load_gait
    from estimator.render import Renderer
    from estimator.skeleton import forward_kinematics

    gait = load_gait()
    n = len(phases)
    w, h = IMAGE_SIZE
    sil = np.zeros((n, h, w), np.uint8)
    j2d = np.zeros((n, 13, 2), np.float32)
    # Group by (shape, style) so that the renderer keeps its meshes.
    keys = list(zip(shapes, styles))
    order = sorted(range(n), key=lambda i: (id(keys[i][0]), id(keys[i][1])))
    renderer = None
    current = None
    done = 0
    try:
        for i in order:
            shape, style = keys[i]
            if (shape, style) != current:
                if renderer is None:
                    renderer = Renderer(shape, image_size=IMAGE_SIZE)
                else:
                    renderer.set_shape(shape)
                current = (shape, style)
            joints = forward_kinematics(gait.angles(np.array([phases[i]]), style), shape)[0]
            centre = joints[:13].mean(0)
            cam = Camera(float(azimuths[i]), float(elevations[i]), distance=float(distances[i]),
                         image_size=IMAGE_SIZE, focal_px=float(focals[i]), target=tuple(centre))
            sil[i], j2d[i] = renderer.render(joints, cam)
            done += 1
            if progress and done % 500 == 0:
                progress(done, n)
    finally:
        if renderer is not None:
            renderer.close()
    return sil, j2d


def training_examples(*, source: str = "auto", verbose: bool = True,
                      cache: bool = True) -> tuple[Examples, str]:
    """The 17,280-example grid and a string naming its source.

    With ``cache``, the output of ``render_examples()`` is kept under
    :func:`cache_dir` (keyed by the default model's examples key).
    """
    if source in ("auto", "render_examples"):
        from estimator import examples as ex_mod

        if hasattr(ex_mod, "render_examples"):
            label = "estimator.examples.render_examples"
            if not cache:
                return ex_mod.render_examples(), label
            from estimator.appearance import _default_examples_key, model_filename

            path = cache_dir() / ("examples-" + model_filename(_default_examples_key()))
            if path.exists():
                return _load(path), label + " (cached)"
            ex = ex_mod.render_examples()
            _save(path, ex)
            return ex, label
        if source == "render_examples":
            raise RuntimeError("estimator.examples.render_examples does not exist yet")
    if source == "stick":
        from estimator._stick_examples import grid_examples

        return grid_examples(), "stick figures (estimator._stick_examples)"
    # The body renderer: "body" = nominal body and average gait; "body-styles" =
    # each example drawn with one of 8 random bodies and gait styles (other seeds
    # than fresh_examples), the same 17,280 grid points.
    from estimator.gait import GaitStyle
    from estimator.skeleton import BodyShape

    if source not in ("auto", "body", "body-styles"):
        raise ValueError(f"unknown source {source!r}")
    spread = source == "body-styles"
    name = "grid_body_styles_v1.npz" if spread else "grid_body_v1.npz"
    label = "body renderer, 8 bodies/gaits" if spread else "body renderer, nominal body"
    path = cache_dir() / name
    if path.exists():
        return _load(path), f"{label} (bench/_appearance_data.py, cached)"
    P, A, E = np.meshgrid(np.arange(N_PHASES) / N_PHASES, AZIMUTHS, ELEVATIONS, indexing="ij")
    n = P.size
    if spread:
        g = np.random.default_rng(1000)
        shapes = [BodyShape.random(g) for _ in range(8)]
        gaits = [GaitStyle.random(g) for _ in range(8)]
        style = g.integers(0, 8, n)
    else:
        shapes, gaits, style = [BodyShape()], [GaitStyle()], np.zeros(n, int)
    t0 = time.perf_counter()
    focal = np.array([0.72 * IMAGE_SIZE[1] / shapes[b].height * 10.0 for b in style])
    sil, j2d = _render(P.ravel(), A.ravel(), E.ravel(), [shapes[b] for b in style],
                       [gaits[b] for b in style], np.full(n, 10.0), focal,
                       progress=(lambda d, t: print(f"  rendered {d}/{t}", flush=True)) if verbose else None)
    if verbose:
        print(f"rendered {n} examples in {time.perf_counter() - t0:.1f} s")
    ex = Examples(silhouettes=sil, joints2d=j2d, phase=P.ravel(), azimuth_deg=A.ravel(),
                  elevation_deg=E.ravel(), style=style)
    _save(path, ex)
    return ex, label


def fresh_examples(n: int, *, seed: int, source: str = "body", n_bodies: int = 20) -> Examples:
    """New walkers: random body and gait (``n_bodies`` of them), off-grid phase and view.

    Phase uniform in [0, 1), azimuth in [0, 360), elevation in [-20, 35]; camera
    distance 6–15 m and focal length such that the body is 120–280 px tall.
    """
    g = np.random.default_rng(seed)
    phase = g.uniform(0, 1, n)
    az = g.uniform(0, 360, n)
    el = g.uniform(-20, 35, n)
    body = g.integers(0, n_bodies, n)
    if source == "stick":
        from estimator._stick_examples import make_examples, style_table

        styles = style_table(n_bodies + 1, rng=seed)[1:]
        return make_examples(phase, az, el, body, styles=styles, px_per_m=g.uniform(45, 95),
                             crop=(200, 140))
    path = cache_dir() / f"fresh_body_v1_{n}_{seed}_{n_bodies}.npz"
    if path.exists():
        return _load(path)
    from estimator.gait import GaitStyle
    from estimator.skeleton import BodyShape

    shapes = [BodyShape.random(g) for _ in range(n_bodies)]
    styles = [GaitStyle.random(g) for _ in range(n_bodies)]
    dist = g.uniform(6.0, 15.0, n)
    px_height = g.uniform(120, 280, n)
    focal = px_height * dist / np.array([shapes[b].height for b in body])
    sil, j2d = _render(phase, az, el, [shapes[b] for b in body], [styles[b] for b in body], dist, focal)
    ex = Examples(silhouettes=sil, joints2d=j2d, phase=phase, azimuth_deg=az, elevation_deg=el,
                  style=body)
    _save(path, ex)
    return ex


def model_for(*, source: str = "auto", n_clusters: int = 100, size=(64, 48), seed: int = 0,
              verbose: bool = True):
    """Build (or load from the bench cache) a model on ``training_examples(source)``."""
    from estimator.appearance import FORMAT_VERSION, build_model, load_model, save_model

    ex, src = training_examples(source=source, verbose=verbose)
    tag = "".join(c if c.isalnum() else "_" for c in src.split(" (")[0])[:40]
    path = cache_dir() / f"model_v{FORMAT_VERSION}_{tag}_{n_clusters}_{size[0]}x{size[1]}_{seed}.npz"
    if path.exists():
        try:
            return load_model(path), ex, src
        except ValueError:
            pass  # stale: rebuild
    t0 = time.perf_counter()
    model = build_model(ex, n_clusters=n_clusters, rng=seed, size=size, provenance={"source": src})
    if verbose:
        print(f"built model ({n_clusters} clusters, canvas {size}) in {time.perf_counter() - t0:.1f} s")
    save_model(model, path)
    return model, ex, src
