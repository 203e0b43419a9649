"""Scores fusion graphs on the held-out examples of a `worldpack fusion-data`
folder (its last tenth, the examples `fusion-train` holds out): PSNR and
sharpness over the whole frame and over the warp's holes, each model folder's
`fusion.onnx` run through ONNX Runtime. How hole heads and detail rules are
chosen before any suite is rolled out (docs/doom.md).

    .venv/bin/python scripts/fusion_heldout.py --data runs/h32/head/data fixtures/doom/geometry_fused CANDIDATE...

Sharpness is `worldpack eval`'s ratio (eval::metrics::sharpness_ratio): each
frame's luma gradient energy over the truth's, the mean over frames; in the
holes only neighbour pairs inside them count, and a frame needs 64 such pairs.
"""

import argparse
import math
from pathlib import Path

import numpy as np
import onnxruntime as ort

LUMA = np.array([0.299, 0.587, 0.114], np.float32).reshape(1, 3, 1, 1)


def held_out(folder: Path):
    """predicted, reference, truth (NCHW in [-1, 1]) and landed (N, 1, H, W) of the last tenth."""
    n = len(np.load(folder / "predicted.npy", mmap_mode="r"))
    cut = n - max(1, n // 10)
    rgb = lambda name: np.load(folder / f"{name}.npy", mmap_mode="r")[cut:].transpose(0, 3, 1, 2).astype(np.float32) / 127.5 - 1
    landed = np.load(folder / "landed.npy", mmap_mode="r")[cut:][:, None].astype(np.float32)
    return rgb("predicted"), rgb("reference"), rgb("truth"), landed


def sharpness(frames, truth, where):
    def luma(x):
        return (np.round((np.clip(x, -1, 1) + 1) * 127.5) * LUMA).sum(1)

    w = where[:, 0]
    wx, wy = w[:, :, 1:] * w[:, :, :-1], w[:, 1:, :] * w[:, :-1, :]
    pairs = wx.sum((1, 2)) + wy.sum((1, 2))

    def energy(x):
        y = luma(x)
        return (((y[:, :, 1:] - y[:, :, :-1]) ** 2 * wx).sum((1, 2)) + ((y[:, 1:, :] - y[:, :-1, :]) ** 2 * wy).sum((1, 2))) / np.maximum(pairs, 1)

    e_truth, e_frames = energy(truth), energy(frames)
    whole = bool(where.min() == 1)
    keep = (e_truth > 0) & (pairs >= (1 if whole else 64))
    return float((e_frames[keep] / e_truth[keep]).mean())


def psnr(frames, truth, where):
    squared = ((np.clip(frames, -1, 1) - truth) * 127.5) ** 2
    return 10 * math.log10(255**2 / ((squared * where).sum() / (where.sum() * 3)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a `worldpack fusion-data` folder")
    parser.add_argument("models", type=Path, nargs="+", help="model folders with a fusion head")
    args = parser.parse_args()
    predicted, reference, truth, landed = held_out(args.data)
    everywhere, holes = np.ones_like(landed), (landed < 0.5).astype(np.float32)
    print(f"{len(truth)} held-out examples of {args.data}; holes in {int(holes.any((1, 2, 3)).sum())} of them, "
          f"{100 * holes.mean():.1f}% of the pixels")
    print(f"{'model':40s} {'PSNR':>6s} {'sharpness':>9s} | {'holes: PSNR':>11s} {'sharpness':>9s}")
    for model in args.models:
        session = ort.InferenceSession(str(model / "fusion.onnx"), providers=["CPUExecutionProvider"])
        frames = np.concatenate([session.run(None, {"predicted": predicted[i:i + 64], "reference": reference[i:i + 64],
                                                    "landed": landed[i:i + 64]})[0] for i in range(0, len(truth), 64)])
        print(f"{str(model):40s} {psnr(frames, truth, everywhere):6.2f} {sharpness(frames, truth, everywhere):9.3f} | "
              f"{psnr(frames, truth, holes):11.2f} {sharpness(frames, truth, holes):9.3f}")


if __name__ == "__main__":
    main()
