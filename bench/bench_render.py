"""Silhouettes rendered per second at 160x320 on one core (target: >= 200/s).

usage: python bench/bench_render.py [--frames N] [--size W,H]

Pins the process to one CPU and llvmpipe to one thread, renders a walk cycle
from a ring of viewpoints with one Renderer (nodes moved, scene reused), and
prints silhouettes/s, ms per silhouette and the ratio to the target.
"""

from __future__ import annotations

import argparse
import os
import time

from _onecore import pin, single_threaded  # noqa: E402

single_threaded()
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from estimator.camera import Camera  # noqa: E402
from estimator.gait import load_gait  # noqa: E402
from estimator.render import Renderer  # noqa: E402
from estimator.skeleton import BodyShape, forward_kinematics  # noqa: E402

TARGET = 200.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=2000)
    parser.add_argument("--size", default="160,320")
    args = parser.parse_args()
    w, h = (int(v) for v in args.size.split(","))
    pin()
    shape = BodyShape()
    poses = forward_kinematics(load_gait().angles(np.linspace(0, 1, 20, endpoint=False)), shape)
    centre = poses[:, :13].mean(axis=(0, 1))
    cams = [
        Camera(az, el, distance=10.0, focal_px=0.8 * h / shape.height * 10.0, image_size=(w, h), target=tuple(centre))
        for az in range(0, 360, 30)
        for el in (-15, 10, 35)
    ]
    with Renderer(shape, image_size=(w, h)) as renderer:
        for k in range(50):  # warm-up: build meshes, compile shaders
            renderer.render(poses[k % 20], cams[k % len(cams)])
        t0 = time.perf_counter()
        cpu0 = time.process_time()
        for k in range(args.frames):
            sil, _ = renderer.render(poses[k % 20], cams[k % len(cams)])
        wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    rate = args.frames / wall
    print(f"render {w}x{h}: {args.frames} silhouettes in {wall:.2f} s on one core (cpu {cpu:.2f} s)")
    print(f"  {rate:.0f} silhouettes/s, {1000 * wall / args.frames:.2f} ms each; target >= {TARGET:.0f}/s: ratio {rate / TARGET:.2f} "
          f"({'met' if rate >= TARGET else 'MISSED'})")


if __name__ == "__main__":
    main()
