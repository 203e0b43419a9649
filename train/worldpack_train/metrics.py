"""PSNR and the sharpness ratio in NumPy, as `worldpack eval` computes them
(eval/src/metrics.rs; tests/test_metrics_pinned.py holds the two together).
Torch-free: scripts, the client's examples and the tests import it, and the
trainer logs with it.

Semantics: images are uint8 RGB, (..., H, W, 3), values 0..255 (`to_u8` turns
the models' [-1, 1] tensors into them as the runtime does). PSNR has a peak of
255 and is capped at 100 dB, so that an identical pair (a copied frame) gives
100, not infinity. The sharpness ratio is a prediction's luma gradient energy
(mean squared difference to the right and below neighbour, BT.601 luma of the
8-bit values) over the truth's: 1 as sharp as the truth, below 1 blurrier,
above 1 noisier; undefined (NaN) for a flat truth."""

from __future__ import annotations

import numpy as np

PSNR_CAP_DB = 100.0
LUMA = np.array([0.299, 0.587, 0.114])


def to_u8(x) -> np.ndarray:
    """A model's frames in [-1, 1], NCHW (a tensor or an array), as uint8 NHWC, rounded half
    up as the runtime rounds them (model/src/generate.rs)."""
    x = np.asarray(x.detach().float().cpu().numpy() if hasattr(x, "detach") else x, dtype=np.float32)
    return np.floor((np.clip(x, -1, 1) + 1) * np.float32(127.5) + 0.5).astype(np.uint8).transpose(0, 2, 3, 1)


def psnr(a: np.ndarray, b: np.ndarray, where: np.ndarray | None = None) -> float:
    """PSNR in dB over every value of `a` and `b` (one frame: eval's per-frame PSNR; a
    batch: pooled over it), or over the pixels where `where` (..., H, W) holds."""
    if a.shape != b.shape:
        raise ValueError(f"psnr: images differ in shape, {a.shape} and {b.shape}")
    d = (a.astype(np.float64) - b.astype(np.float64)) ** 2
    if where is not None:
        w = np.broadcast_to(np.asarray(where, dtype=bool)[..., None], d.shape)
        if not w.any():
            return float("nan")
        d = d[w]
    mse = d.mean()
    return PSNR_CAP_DB if mse == 0 else float(min(10 * np.log10(255.0**2 / mse), PSNR_CAP_DB))


def gradient_energy(rgb: np.ndarray, where: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per image of (N, H, W, 3) uint8: the mean squared luma difference over neighbour pairs
    (right and below) whose two pixels `where` (N, H, W) holds, and how many pairs that was."""
    y = rgb.astype(np.float64) @ LUMA
    m = np.ones(y.shape, dtype=bool) if where is None else np.asarray(where, dtype=bool)
    mx, my = m[:, :, 1:] & m[:, :, :-1], m[:, 1:, :] & m[:, :-1, :]
    total = ((y[:, :, 1:] - y[:, :, :-1]) ** 2 * mx).sum((1, 2)) + ((y[:, 1:, :] - y[:, :-1, :]) ** 2 * my).sum((1, 2))
    pairs = mx.sum((1, 2)) + my.sum((1, 2))
    return np.where(pairs > 0, total / np.maximum(pairs, 1), 0.0), pairs


def sharpness_ratio(predicted: np.ndarray, truth: np.ndarray, where: np.ndarray | None = None, min_pairs: int = 1) -> float:
    """The mean over frames of the prediction's gradient energy over the truth's, counting
    frames whose truth is not flat and, with `where`, that have `min_pairs` pairs inside it
    (eval uses 64 for the warp's holes). One frame: eval::metrics::sharpness_ratio(_where)."""
    one = predicted.ndim == 3
    predicted, truth = (predicted[None], truth[None]) if one else (predicted, truth)
    if where is not None and one:
        where = np.asarray(where)[None]
    e_truth, pairs = gradient_energy(truth, where)
    e_pred, _ = gradient_energy(predicted, where)
    keep = (e_truth > 0) & (pairs >= max(min_pairs, 1))
    return float((e_pred[keep] / e_truth[keep]).mean()) if keep.any() else float("nan")
