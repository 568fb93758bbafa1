"""Offline feedback on damaged silhouettes: can it hurt? (issue 17, docs/FEEDBACK.md).

Synthetic walks (2-3 cameras, 30 frames; every third driven by the CMU
recording 16_15 like ``posecal synth --motion``), each damage kind of
:mod:`estimator.damage` drawn onto the true masks (and ``none``: clean input),
then ``posecal refine``'s path (:func:`capture.refine.refine_sequence`): IoU
of the input and of the refined silhouette with the true mask, per damage
kind. Then the same with a deliberately wrong estimate (every camera's
viewpoint turned by 90 deg, :func:`estimator.prior.turn_viewpoints`): the
refined silhouettes must equal the input.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python bench/eval_refine_damage.py [--sequences 12] [--png PATH]
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from capture.refine import refine_sequence  # noqa: E402
from capture.scene import iou  # noqa: E402
from estimator.damage import DAMAGE_KINDS, damage_sequence  # noqa: E402
from estimator.prior import FEEDBACK, PriorConfig, turn_viewpoints  # noqa: E402
from estimator.sequence import Sequence  # noqa: E402
from estimator.synth import SynthSpec, synthesize  # noqa: E402

MOTION = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "mocap", "16_15.bvh")


def make_sequences(n: int, *, n_frames: int = 30, size: tuple[int, int] = (320, 240)) -> list[Sequence]:
    """``n`` synthetic walks: 2 or 3 cameras, every third one driven by the CMU recording (when present)."""
    from estimator.mocap import read_motion

    motion = read_motion(MOTION) if os.path.exists(MOTION) else None
    return [synthesize(SynthSpec(n_cameras=2 + seed % 2, n_frames=n_frames, seed=seed, image_size=size),
                       motion=motion if seed % 3 == 2 else None) for seed in range(n)]


def damaged(seq: Sequence, kind: str, seed: int) -> Sequence:
    """The sequence with ``kind`` damage on every silhouette (``"none"``: as it is)."""
    if kind == "none":
        return seq
    sils = damage_sequence(seq.silhouettes, kind, seed=seed, truth=seq.truth)
    return Sequence(fps=seq.fps, cameras=list(seq.cameras), image_size=seq.image_size, silhouettes=sils,
                    truth=seq.truth)


def frame_ious(truth: Sequence, sils: dict[str, list[np.ndarray | None]]) -> np.ndarray:
    """IoU with the true mask of every frame that has one (missing silhouette = 0)."""
    out = []
    for cam in truth.cameras:
        for t, m in zip(truth.silhouettes[cam], sils[cam]):
            if t is not None and t.any():
                out.append(0.0 if m is None else iou(m > 0, t > 0))
    return np.array(out)


def changed_frames(a: Sequence, b: Sequence) -> int:
    """Frames whose silhouettes differ in any pixel."""
    return sum(int((x is None) != (y is None) or (x is not None and not np.array_equal(x > 0, y > 0)))
               for cam in a.cameras for x, y in zip(a.silhouettes[cam], b.silhouettes[cam]))


def evaluate(seqs: list[Sequence], model, renderer, config: PriorConfig, kinds=DAMAGE_KINDS, *,
             wrong: bool = True, log=print) -> dict[str, dict]:
    """Per damage kind: per-frame input and refined IoU, frames changed (right and 90-deg-wrong estimate)."""
    rows = {}
    for kind in kinds:
        before, after, changed, changed_wrong, frames = [], [], 0, 0, 0
        for k, seq in enumerate(seqs):
            inp = damaged(seq, kind, seed=100 + k)
            res = refine_sequence(inp, model, renderer=renderer, config=config)
            before.append(frame_ious(seq, inp.silhouettes))
            after.append(frame_ious(seq, res.sequence.silhouettes))
            changed += changed_frames(inp, res.sequence)
            frames += sum(len(v) for v in inp.silhouettes.values())
            if wrong:
                bad = refine_sequence(inp, model, renderer=renderer, config=config,
                                      estimate=turn_viewpoints(res.estimate, 90.0))
                changed_wrong += changed_frames(inp, bad.sequence)
        b, a = np.concatenate(before), np.concatenate(after)
        rows[kind] = dict(frames=frames, input=b, refined=a, changed=changed, changed_wrong=changed_wrong)
        log(f"{kind:14s} IoU {b.mean():.3f} -> {a.mean():.3f} ({a.mean() - b.mean():+.3f}); "
            f"worse by >0.01 on {int(np.sum(a < b - 0.01))} frames; changed {changed}/{frames}, "
            f"with a 90-deg-wrong estimate {changed_wrong}")
    return rows


def table(rows: dict[str, dict]) -> str:
    """Markdown table of :func:`evaluate`'s rows."""
    lines = ["| damage | frames | input IoU | refined IoU | change | frames worse by > 0.01 | frames changed | "
             "frames changed, 90-deg-wrong estimate |", "|---|---|---|---|---|---|---|---|"]
    for kind, r in rows.items():
        b, a = r["input"], r["refined"]
        lines.append(f"| {kind} | {r['frames']} | {b.mean():.3f} | {a.mean():.3f} | {a.mean() - b.mean():+.3f} | "
                     f"{int(np.sum(a < b - 0.01))} | {r['changed']} | {r['changed_wrong']} |")
    return "\n".join(lines)


def plot(rows: dict[str, dict], path: str) -> None:
    """Bar chart of the mean IoU change per damage kind, with the per-frame spread."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = list(rows)
    d = [rows[k]["refined"] - rows[k]["input"] for k in kinds]
    fig, ax = plt.subplots(figsize=(8, 3.6))
    ax.axhline(0, color="k", lw=0.8)
    ax.boxplot(d, positions=range(len(kinds)), widths=0.5, showfliers=False, medianprops=dict(color="0.4"))
    ax.bar(range(len(kinds)), [x.mean() for x in d], width=0.3, color="tab:blue", alpha=0.6, label="mean")
    ax.set_xticks(range(len(kinds)), [f"{k}\n{x.mean():+.3f}" for k, x in zip(kinds, d)])
    ax.set_ylabel("IoU refined - input")
    ax.set_title("posecal refine on damaged silhouettes (bars: mean; boxes: frames)")
    ax.legend(loc="upper left")
    fig.tight_layout()
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    fig.savefig(path, dpi=110)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sequences", type=int, default=12)
    ap.add_argument("--kinds", default=",".join(("none",) + DAMAGE_KINDS), help="damage kinds; none = clean input")
    ap.add_argument("--png", default="docs/img/refine_damage.png")
    args = ap.parse_args()
    from estimator.render import Renderer
    from service.cli.model import get_default_model

    t0 = time.perf_counter()
    model = get_default_model()
    seqs = make_sequences(args.sequences)
    with Renderer(FEEDBACK.body) as renderer:
        rows = evaluate(seqs, model, renderer, FEEDBACK, args.kinds.split(","))
    print(table(rows))
    gains = {k: r["refined"].mean() - r["input"].mean() for k, r in rows.items()}
    print("targets: change >= 0 on every damage:",
          "MET" if min(g for k, g in gains.items() if k != "none") >= 0 else "NOT MET",
          "| >= +0.05 on holes, cut_limb:",
          "MET" if all(gains.get(k, 1.0) >= 0.05 for k in ("holes", "cut_limb")) else "NOT MET",
          "| 0 frames changed by a wrong estimate:",
          "MET" if sum(r["changed_wrong"] for r in rows.values()) == 0 else "NOT MET")
    if args.png:
        plot(rows, args.png)
        print(f"wrote {args.png}")
    print(f"{len(seqs)} sequences, {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
