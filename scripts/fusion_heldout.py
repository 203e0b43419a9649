"""Scores fusion graphs on the held-out examples of a `worldpack fusion-data`
folder (its last tenth, the examples `fusion-train` holds out): PSNR and
sharpness over the whole frame and over the warp's holes, each model folder's
`fusion.onnx` run through ONNX Runtime. How hole heads and detail rules are
chosen before any suite is rolled out (docs/doom.md).

    .venv/bin/python scripts/fusion_heldout.py --data runs/h32/head/data fixtures/doom/geometry_fused CANDIDATE...

PSNR and sharpness are worldpack_train.metrics (`worldpack eval`'s, pinned by
tests/test_metrics_pinned.py); in the holes only neighbour pairs inside them
count, and a frame needs 64 such pairs.
"""

import argparse
from pathlib import Path

import numpy as np
import onnxruntime as ort
from worldpack_train.metrics import psnr, sharpness_ratio, to_u8


def held_out(folder: Path):
    """predicted, reference, truth (NCHW in [-1, 1]) and landed (N, 1, H, W) of the last tenth."""
    n = len(np.load(folder / "predicted.npy", mmap_mode="r"))
    cut = n - max(1, n // 10)
    rgb = lambda name: np.load(folder / f"{name}.npy", mmap_mode="r")[cut:].transpose(0, 3, 1, 2).astype(np.float32) / 127.5 - 1
    landed = np.load(folder / "landed.npy", mmap_mode="r")[cut:][:, None].astype(np.float32)
    return rgb("predicted"), rgb("reference"), rgb("truth"), landed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, required=True, help="a `worldpack fusion-data` folder")
    parser.add_argument("models", type=Path, nargs="+", help="model folders with a fusion head")
    args = parser.parse_args()
    predicted, reference, truth, landed = held_out(args.data)
    holes = landed[:, 0] < 0.5
    truth = to_u8(truth)
    print(f"{len(truth)} held-out examples of {args.data}; holes in {int(holes.any((1, 2)).sum())} of them, "
          f"{100 * holes.mean():.1f}% of the pixels")
    print(f"{'model':40s} {'PSNR':>6s} {'sharpness':>9s} | {'holes: PSNR':>11s} {'sharpness':>9s}")
    for model in args.models:
        session = ort.InferenceSession(str(model / "fusion.onnx"), providers=["CPUExecutionProvider"])
        frames = np.concatenate([session.run(None, {"predicted": predicted[i:i + 64], "reference": reference[i:i + 64],
                                                    "landed": landed[i:i + 64]})[0] for i in range(0, len(truth), 64)])
        frames = to_u8(frames)
        print(f"{str(model):40s} {psnr(frames, truth):6.2f} {sharpness_ratio(frames, truth):9.3f} | "
              f"{psnr(frames, truth, holes):11.2f} {sharpness_ratio(frames, truth, holes, min_pairs=64):9.3f}")


if __name__ == "__main__":
    main()
