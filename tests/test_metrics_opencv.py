"""The Rust image metrics (`worldpack compare`, the ones `eval` and `probe`
use) against independent OpenCV implementations: PSNR from cv2.PSNR, and
SSIM (11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, window positions
inside the image, mean over channels) from cv2.GaussianBlur."""

import json
import os
import subprocess

import cv2
import numpy as np
import pytest

BIN = os.environ.get("WORLDPACK_BIN", os.path.join(os.path.dirname(__file__), "..", "target", "release", "worldpack"))


def compare(tmp_path, a, b):
    pa, pb = tmp_path / "a.png", tmp_path / "b.png"
    cv2.imwrite(str(pa), cv2.cvtColor(a, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(pb), cv2.cvtColor(b, cv2.COLOR_RGB2BGR))
    out = subprocess.run([BIN, "compare", str(pa), str(pb)], capture_output=True, text=True, check=True)
    return json.loads(out.stdout)


def ssim_opencv(a, b):
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5)[5:-5, 5:-5]  # the window positions that fit
    total = 0.0
    for c in range(3):
        x, y = a[..., c].astype(np.float64), b[..., c].astype(np.float64)
        mx, my = blur(x), blur(y)
        vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
        total += np.mean(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
    return total / 3


def texture(rng, h, w):
    base = cv2.resize(rng.integers(0, 256, (h // 8, w // 8, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_CUBIC)
    return np.clip(base.astype(np.int16) + rng.integers(-20, 21, (h, w, 3)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("kind", ["noise", "blur", "shift", "jpeg", "unrelated"])
@pytest.mark.parametrize("size", [(64, 64), (48, 80)])
def test_metrics_match_opencv(tmp_path, kind, size):
    rng = np.random.default_rng(hash((kind, size)) % 2**32)
    a = texture(rng, *size)
    if kind == "noise":
        b = np.clip(a.astype(np.int16) + rng.integers(-30, 31, a.shape), 0, 255).astype(np.uint8)
    elif kind == "blur":
        b = cv2.GaussianBlur(a, (5, 5), 1.2)
    elif kind == "shift":
        b = np.roll(a, 2, axis=1)
    elif kind == "jpeg":
        ok, buf = cv2.imencode(".jpg", a, [cv2.IMWRITE_JPEG_QUALITY, 30])
        b = cv2.imdecode(buf, cv2.IMREAD_COLOR)
    else:
        b = texture(rng, *size)
    got = compare(tmp_path, a, b)
    assert (got["width"], got["height"]) == (size[1], size[0])
    assert got["psnr"] == pytest.approx(cv2.PSNR(a, b), abs=1e-9)
    assert got["ssim"] == pytest.approx(ssim_opencv(a, b), abs=1e-9)


def test_identical_images_and_bad_input(tmp_path):
    a = texture(np.random.default_rng(0), 32, 32)
    got = compare(tmp_path, a, a)
    assert got["psnr"] == 100.0 and got["ssim"] == pytest.approx(1.0, abs=1e-12)  # PSNR is capped, not infinite
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), a[:16, :16])
    out = subprocess.run([BIN, "compare", str(tmp_path / "a.png"), str(small)], capture_output=True, text=True)
    assert out.returncode == 2 and "differ in size" in out.stderr
    out = subprocess.run([BIN, "compare", str(tmp_path / "a.png"), str(tmp_path / "missing.png")], capture_output=True, text=True)
    assert out.returncode == 2 and "missing.png" in out.stderr
