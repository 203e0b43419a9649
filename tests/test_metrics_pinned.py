"""The Python metrics (worldpack_train.metrics: what the trainer, the scripts and the
client's examples score with) against the Rust ones `eval` reports (`worldpack compare`):
PSNR, its 100 dB cap for identical frames, and the sharpness ratio, including a flat truth."""

import cv2
import numpy as np
import pytest
from test_metrics_opencv import compare
from worldpack_train import metrics


def pairs():
    rng = np.random.default_rng(7)
    truth = cv2.resize(rng.integers(0, 256, (8, 8, 3), dtype=np.uint8), (64, 64), interpolation=cv2.INTER_CUBIC)
    noisy = np.clip(truth.astype(np.int16) + rng.integers(-30, 31, truth.shape), 0, 255).astype(np.uint8)
    yield "blurred", cv2.GaussianBlur(truth, (7, 7), 2.0), truth
    yield "noisy", noisy, truth
    yield "identical", truth, truth.copy()
    yield "one value off", np.where(np.arange(truth.size).reshape(truth.shape) == 5, truth ^ 1, truth).astype(np.uint8), truth
    yield "flat truth", noisy, np.full_like(truth, 90)


@pytest.mark.parametrize("case,predicted,truth", list(pairs()), ids=[c for c, _, _ in pairs()])
def test_python_metrics_match_the_rust_ones(tmp_path, case, predicted, truth):
    rust = compare(tmp_path, predicted, truth)
    assert metrics.psnr(predicted, truth) == pytest.approx(rust["psnr"], abs=1e-9)
    ours = metrics.sharpness_ratio(predicted, truth)
    if rust["sharpness"] is None:
        assert np.isnan(ours), f"{case}: the Rust ratio is undefined for a flat truth, Python's {ours}"
    else:
        assert ours == pytest.approx(rust["sharpness"], rel=1e-9)


def test_semantics_the_docs_state():
    a = np.zeros((4, 4, 3), np.uint8)
    assert metrics.psnr(a, a) == metrics.PSNR_CAP_DB == 100.0
    b = a.copy()
    b[0, 0, 0] = 255  # one value of 48 at the full range: mse 255²/48
    assert metrics.psnr(a, b) == pytest.approx(10 * np.log10(48))
    # [-1, 1] frames round as the runtime rounds them.
    assert metrics.to_u8(np.array([[[[-1.0]], [[0.0]], [[1.0]]]])).tolist() == [[[[0, 128, 255]]]]
