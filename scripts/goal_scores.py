"""Which score of a view against a goal view ranks poses by how near the goal they are, in Doom.

A planner that scores imagined frames against a goal image needs a score that rises as the
pose nears the goal's. For goal poses drawn on the held-out maps (map20, map29, map18), the
engine renders views at poses around each goal (0 to 1.3 m away, turned 0 to 45°), and each
score's rank correlation with nearness (distance / 0.5 m + turn / 20°, the planner's success
scale) is reported, with how often the best-scored view (the goal's own excluded) lies within
0.5 m and 20° of the goal. Scores: PSNR (the server's `psnr_db`), PSNR of 4× and 8× smaller
pictures, SSIM (7×7 Gaussian windows, grey), the served Doom model's latent distance (the
server's `latent_mse`, negated) and the distance of edge maps.

    .venv/bin/python scripts/goal_scores.py --maps 12        # 3 goals a map start, 36 goals

Needs doom/requirements.txt (vizdoom, opencv) and onnxruntime (tests/requirements.txt).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "doom"), str(ROOT / "train")]
from worldpack_doom import engine as E, suite as S, walk as W  # noqa: E402
from worldpack_train.metrics import psnr  # noqa: E402

DISTANCES_M = [0.0, 0.22, 0.43, 0.65, 0.87, 1.3]
TURNS_DEG = [0, 15, 30, 45]


def grey(x: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float64)


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    a, b = grey(a), grey(b)
    blur = lambda x: cv2.GaussianBlur(x, (7, 7), 1.5)  # noqa: E731
    ma, mb = blur(a), blur(b)
    va, vb, cov = blur(a * a) - ma * ma, blur(b * b) - mb * mb, blur(a * b) - ma * mb
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    return float((((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma * ma + mb * mb + c1) * (va + vb + c2))).mean())


def smaller(x: np.ndarray, k: int) -> np.ndarray:
    return cv2.resize(x, (x.shape[1] // k, x.shape[0] // k), interpolation=cv2.INTER_AREA)


def edges(x: np.ndarray) -> np.ndarray:
    g = grey(x).astype(np.float32)
    return np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))


def ranks(x: np.ndarray) -> np.ndarray:
    return np.argsort(np.argsort(x)).astype(float)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--maps", type=int, default=12, help="map starts (map20, map29, map18 in turn), 3 goals each")
    ap.add_argument("--seed", type=int, default=300, help="start k draws its goals from seed + k")
    ap.add_argument("--model", default=str(ROOT / "fixtures" / "doom" / "geometry_fused"), help="whose encoder gives the latents")
    a = ap.parse_args()
    encoder = ort.InferenceSession(str(Path(a.model) / "encoder.onnx"), providers=["CPUExecutionProvider"])

    def latent(rgb: np.ndarray) -> np.ndarray:
        return encoder.run(None, {"image": rgb.astype(np.float32).transpose(2, 0, 1)[None] / 127.5 - 1.0})[0][0]

    scores = {
        "PSNR": lambda v, g: psnr(v, g),
        "PSNR, 4x smaller": lambda v, g: psnr(smaller(v, 4), smaller(g, 4)),
        "PSNR, 8x smaller": lambda v, g: psnr(smaller(v, 8), smaller(g, 8)),
        "SSIM": ssim,
        "latent distance": lambda v, g: -float(((latent(v) - latent(g)) ** 2).mean()),
        "edge-map distance": lambda v, g: -float(np.abs(edges(v) - edges(g)).mean()),
    }
    correlation = {k: [] for k in scores}
    best_within = {k: [] for k in scores}
    for k in range(a.maps):
        rng = np.random.default_rng(a.seed + k)
        engine = E.Engine(S.TEST_MAPS[k % len(S.TEST_MAPS)], seed=0)
        geom = W.Geometry(engine.sectors())
        for p, angle in W.start_points(engine.sectors(), geom, 3, rng):
            def view(x, turn):
                return S.to_frame(engine.view_at(x[0], x[1], turn))[0]
            goal = view(p, angle)
            around = []
            for d in DISTANCES_M:
                for t in TURNS_DEG:
                    q = p + d * E.UNITS_PER_METRE * W.heading_vector(rng.uniform(0.0, 360.0))
                    if d > 0 and not geom.free(p, q):
                        continue
                    around.append((d, t, view(q, angle + rng.choice([-1, 1]) * t)))
            nearness = np.array([d / 0.5 + t / 20.0 for d, t, _ in around])
            within = np.array([d <= 0.5 and t <= 20 for d, t, _ in around])
            others = nearness > 0
            for name, f in scores.items():
                s = np.array([f(v, goal) for _, _, v in around])
                s[~np.isfinite(s)] = 1e9  # the goal's own view: PSNR is infinite
                correlation[name].append(float(np.corrcoef(ranks(s), ranks(-nearness))[0, 1]))
                best_within[name].append(bool(within[others][np.argmax(s[others])]))
        engine.close()
    n = len(correlation["PSNR"])
    print(f"{n} goals on {a.maps} map starts (seeds {a.seed}..{a.seed + a.maps - 1}), {len(DISTANCES_M) * len(TURNS_DEG)} views round each")
    print(f"{'score':<20} {'rank correlation with nearness':>32} {'best view within reach':>24}")
    for name in scores:
        r = np.array(correlation[name])
        rng = np.random.default_rng(0)
        boot = r[rng.integers(0, n, (10000, n))].mean(axis=1)
        print(f"{name:<20} {r.mean():>+14.3f} [{np.percentile(boot, 2.5):+.3f}, {np.percentile(boot, 97.5):+.3f}] {np.mean(best_within[name]):>24.2f}")


if __name__ == "__main__":
    main()
