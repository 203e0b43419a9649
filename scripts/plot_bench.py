"""Log-log plot of selection latency against stored frames.

Reads the JSON of `worldpack bench select --json` (one file per workload) and
draws median latency of each method with OpenCV (already in the test venv).

    .venv/bin/python scripts/plot_bench.py docs/bench/select-walk.json docs/bench/select-loop.json -o docs/bench/select.png
"""

import argparse
import json
import math

import cv2
import numpy as np

W, H, MARGIN = 900, 560, 80
METHODS = [("indexed_median_ms", "indexed exact", (200, 90, 20)),
           ("brute_exact_median_ms", "brute-force exact", (40, 140, 40)),
           ("brute_mc_median_ms", "brute-force Monte Carlo 10k", (30, 30, 200))]
DASH = {"walk": False, "loop": True}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("inputs", nargs="+")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args()
    runs = [json.load(open(p)) for p in args.inputs]
    xs = [r["frames"] for run in runs for r in run["rows"]]
    ys = [r[key] for run in runs for r in run["rows"] for key, _, _ in METHODS]
    x0, x1 = math.floor(math.log10(min(xs))), math.ceil(math.log10(max(xs)))
    y0, y1 = math.floor(math.log10(min(ys))), math.ceil(math.log10(max(ys)))

    def to_px(x, y):
        u = MARGIN + (math.log10(x) - x0) / (x1 - x0) * (W - 2 * MARGIN)
        v = H - MARGIN - (math.log10(y) - y0) / (y1 - y0) * (H - 2 * MARGIN)
        return int(round(u)), int(round(v))

    img = np.full((H, W, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    for e in range(x0, x1 + 1):
        u, _ = to_px(10 ** e, 10 ** y0)
        cv2.line(img, (u, MARGIN), (u, H - MARGIN), (225, 225, 225), 1)
        cv2.putText(img, f"1e{e}", (u - 15, H - MARGIN + 22), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for e in range(y0, y1 + 1):
        _, v = to_px(10 ** x0, 10 ** e)
        cv2.line(img, (MARGIN, v), (W - MARGIN, v), (225, 225, 225), 1)
        cv2.putText(img, f"1e{e} ms", (8, v + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (MARGIN, MARGIN), (W - MARGIN, H - MARGIN), (0, 0, 0), 1)
    cv2.putText(img, "stored frames", (W // 2 - 50, H - 25), font, 0.55, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "selection latency (median, one core): solid = walk, dashed = loop", (MARGIN, 40), font, 0.6,
                (0, 0, 0), 1, cv2.LINE_AA)
    for run in runs:
        dashed = DASH.get(run["workload"], False)
        for key, _, colour in METHODS:
            pts = [to_px(r["frames"], r[key]) for r in run["rows"]]
            for a, b in zip(pts, pts[1:]):
                if dashed:
                    n = max(1, int(np.hypot(b[0] - a[0], b[1] - a[1]) // 8))
                    for i in range(0, n, 2):
                        p = (int(a[0] + (b[0] - a[0]) * i / n), int(a[1] + (b[1] - a[1]) * i / n))
                        q = (int(a[0] + (b[0] - a[0]) * (i + 1) / n), int(a[1] + (b[1] - a[1]) * (i + 1) / n))
                        cv2.line(img, p, q, colour, 2, cv2.LINE_AA)
                else:
                    cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
            for p in pts:
                cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
    for i, (_, label, colour) in enumerate(METHODS):
        y = MARGIN + 20 + 22 * i
        cv2.line(img, (MARGIN + 15, y - 4), (MARGIN + 45, y - 4), colour, 3)
        cv2.putText(img, label, (MARGIN + 52, y), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(args.output, img)


if __name__ == "__main__":
    main()
