"""The main job's speed against its accuracy: one point per served configuration.

Each point joins a `worldpack bench walk --json` file (x: the whole step's p50
at one session, in ms) with a row of a `worldpack eval` results.json (y: pooled
return-leg PSNR and sharpness ratio), drawn with OpenCV (in the test venv):

    .venv/bin/python scripts/plot_speed.py -o docs/bench/speed.png \\
        --point "10 DDIM steps=docs/bench/walk-10step.json:runs/distill/eval-test/results.json:fused_covisible" ...

With `--record FILE` (docs/bench/speed-points.json) the chart draws every point the
record holds, each `--point` added or replacing the one of its label, and the record is
written back with each point's sources: eval outputs live in git-ignored run folders, so a
point measured once stays on the chart after its run folder is gone.
"""

import argparse
import json
import os

import cv2
import numpy as np

W, H, L, R, T, B = 520, 420, 70, 20, 50, 60
COLOURS = [(200, 90, 20), (40, 140, 40), (30, 30, 200), (150, 60, 150), (20, 140, 170), (90, 90, 90), (0, 110, 230)]


def point(spec):
    label, rest = spec.split("=", 1)
    bench, results, row = rest.split(":")
    walk = json.load(open(bench))
    one = next(r for r in walk["rows"] if r["sessions"] == 1)
    ms = one["p50_ms"][walk["stages"].index("total")]
    pooled = next(p for p in json.load(open(results))["pooled"] if p["row"] == row)
    return {"label": label, "ms": ms, "psnr": pooled["psnr"]["mean"], "sharpness": pooled["sharpness"]["mean"],
            "bench": bench, "results": results, "row": row}


def panel(points, key, title):
    img = np.full((H, W, 3), 255, np.uint8)
    xs, ys = [p["ms"] for p in points], [p[key] for p in points]
    x0, x1 = 0.0, max(max(xs), 40) * 1.1  # the 40 ms bar always in view
    pad = (max(ys) - min(ys)) * 0.15 or 0.1
    y0, y1 = min(ys) - pad, max(ys) + pad
    px = lambda x, y: (int(L + (x - x0) / (x1 - x0) * (W - L - R)), int(H - B - (y - y0) / (y1 - y0) * (H - T - B)))
    font = cv2.FONT_HERSHEY_SIMPLEX
    for k in range(6):
        y = y0 + (y1 - y0) * k / 5
        _, yy = px(x0, y)
        cv2.line(img, (L, yy), (W - R, yy), (230, 230, 230), 1)
        cv2.putText(img, f"{y:.3f}" if key == "sharpness" else f"{y:.2f}", (8, yy + 4), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    step = 20 if x1 > 80 else 10
    for x in range(0, int(x1) + 1, step):
        xx, _ = px(x, y0)
        cv2.line(img, (xx, T), (xx, H - B), (230, 230, 230), 1)
        cv2.putText(img, str(x), (xx - 8, H - B + 18), font, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    xx, _ = px(40, y0)
    cv2.line(img, (xx, T), (xx, H - B), (0, 0, 220), 1)  # the bar: p50 <= 40 ms
    cv2.putText(img, "40 ms", (xx + 4, H - B - 8), font, 0.4, (0, 0, 220), 1, cv2.LINE_AA)
    cv2.rectangle(img, (L, T), (W - R, H - B), (0, 0, 0), 1)
    cv2.putText(img, title, (L, T - 18), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "ms per step, p50, one session, one core", (L + 40, H - 18), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    dots = [px(p["ms"], p[key]) for p in points]
    taken = [(x - 6, y - 6, x + 6, y + 6) for x, y in dots]  # boxes labels must not cover
    for i, (p, q) in enumerate(zip(points, dots)):
        cv2.circle(img, q, 6, COLOURS[i % len(COLOURS)], -1, cv2.LINE_AA)
        (width, height), _ = cv2.getTextSize(p["label"], font, 0.4, 1)
        # Above right, below right, above left, below left: the first that stays inside the
        # plot and clear of the dots and the labels placed so far.
        spots = [(q[0] + 9, q[1] - 8), (q[0] + 9, q[1] + 8 + height), (q[0] - 9 - width, q[1] - 8), (q[0] - 9 - width, q[1] + 8 + height)]
        box = lambda x, y: (x, y - height, x + width, y + 2)
        inside = lambda b: b[0] >= L and b[2] <= W - R and b[1] >= T and b[3] <= H - B
        clear = lambda b: all(b[2] < t[0] or t[2] < b[0] or b[3] < t[1] or t[3] < b[1] for t in taken)
        x, y = next((s for s in spots if inside(box(*s)) and clear(box(*s))), next((s for s in spots if inside(box(*s))), spots[0]))
        taken.append(box(x, y))
        cv2.putText(img, p["label"], (x, y), font, 0.4, COLOURS[i % len(COLOURS)], 1, cv2.LINE_AA)
    return img


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--point", action="append", default=[], help="LABEL=BENCH_JSON:RESULTS_JSON:ROW")
    ap.add_argument("--record", help="a JSON list of points measured before: drawn, updated and written back")
    ap.add_argument("-o", "--out", required=True)
    a = ap.parse_args()
    points = json.load(open(a.record)) if a.record and os.path.exists(a.record) else []
    for p in map(point, a.point):
        points = [q for q in points if q["label"] != p["label"]] + [p]
    if not points:
        ap.error("nothing to draw: give --point, or --record with points in it")
    if a.record:
        with open(a.record, "w") as f:
            json.dump(points, f, indent=1)
            f.write("\n")
    img = np.hstack([panel(points, "psnr", "return-leg PSNR (dB), 48 trajectories"),
                     panel(points, "sharpness", "sharpness ratio (1 = the truth's edges)")])
    cv2.imwrite(a.out, img)
    for p in points:
        print(f"{p['label']:<28} {p['ms']:7.1f} ms  {p['psnr']:6.2f} dB  sharpness {p['sharpness']:.3f}")


if __name__ == "__main__":
    main()
