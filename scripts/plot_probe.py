"""Pictures for docs/probe.md, drawn with OpenCV (already in the test venv).

    # training loss of the four variants, fine-tunes drawn from where the baseline ended
    .venv/bin/python scripts/plot_probe.py loss runs/small/log.jsonl -o docs/probe/training_loss.png
    # several runs: a stage in a later log replaces the same stage of an earlier one
    # (here the baseline of runs/small with the fine-tunes of runs/geo)
    .venv/bin/python scripts/plot_probe.py loss runs/small/log.jsonl runs/geo/log.jsonl -o docs/probe/training_loss.png
    # return-leg PSNR difference to the baseline, with 95% intervals, from `worldpack probe --out`
    .venv/bin/python scripts/plot_probe.py probe docs/probe/probe-first-variants.json -o docs/probe/probe-first-variants.png
"""

import argparse
import json

import cv2
import numpy as np

FONT = cv2.FONT_HERSHEY_SIMPLEX
BLACK, GREY = (0, 0, 0), (225, 225, 225)
COLOURS = {"baseline": (60, 60, 60), "nearest_frame_packing": (40, 140, 40), "memory_retrieval": (200, 120, 30),
           "worldpack": (30, 30, 200), "worldpack_keep_last": (0, 90, 255)}


def text(img, s, xy, scale=0.5, colour=BLACK):
    cv2.putText(img, s, xy, FONT, scale, colour, 1, cv2.LINE_AA)


def nice_ticks(lo, hi, n=6):
    step = 10 ** np.floor(np.log10((hi - lo) / n))
    for m in (1, 2, 5, 10):
        if (hi - lo) / (step * m) <= n:
            step *= m
            break
    return np.arange(np.ceil(lo / step) * step, hi + 1e-9, step)


def loss(args):
    stages = {}
    for path in args.input:
        here = {}
        for r in (json.loads(line) for line in open(path)):
            if r["stage"].startswith("cdit-"):
                here.setdefault(r["stage"][5:], []).append((r["step"], r["loss"]))
        stages.update(here)
    if "baseline" not in stages:
        raise SystemExit(f"{' '.join(args.input)}: no cdit-baseline records")
    base_end = max(s for s, _ in stages["baseline"])
    curves = {}
    for name, pts in stages.items():
        if name not in COLOURS:
            continue  # e.g. a from-scratch run kept for reference
        pts = sorted(pts)
        offset = 0 if name == "baseline" else base_end  # fine-tunes continue from the baseline
        steps = np.array([s for s, _ in pts]) + offset
        vals = np.array([v for _, v in pts])
        k = max(1, min(len(vals) // 10, 20))
        smooth = np.convolve(vals, np.ones(k) / k, mode="valid")
        curves[name] = (steps[k - 1:], smooth)
    W, H, M = 900, 520, 70
    xs = np.concatenate([c[0] for c in curves.values()])
    ys = np.concatenate([c[1] for c in curves.values()])
    x0, x1 = 0, xs.max()
    y0, y1 = 0.0, float(np.percentile(ys, 99)) * 1.1
    px = lambda x, y: (int(M + (x - x0) / (x1 - x0) * (W - 2 * M)), int(H - M - (min(y, y1) - y0) / (y1 - y0) * (H - 2 * M)))
    img = np.full((H, W, 3), 255, np.uint8)
    for t in nice_ticks(y0, y1):
        u, v = px(x0, t)
        cv2.line(img, (M, v), (W - M, v), GREY, 1)
        text(img, f"{t:.3f}", (8, v + 5), 0.45)
    for t in nice_ticks(x0, x1):
        u, v = px(t, y0)
        cv2.line(img, (u, M), (u, H - M), GREY, 1)
        text(img, f"{int(t)}", (u - 18, H - M + 20), 0.45)
    cv2.rectangle(img, (M, M), (W - M, H - M), BLACK, 1)
    text(img, "training loss (eps MSE, moving average) against step; fine-tunes start at the baseline's end", (M, 35), 0.55)
    text(img, "step", (W // 2 - 20, H - 20), 0.55)
    for i, (name, (s, v)) in enumerate(curves.items()):
        pts = np.array([px(a, b) for a, b in zip(s, v)], np.int32)
        cv2.polylines(img, [pts], False, COLOURS[name], 2, cv2.LINE_AA)
        y = M + 22 + 22 * i
        cv2.line(img, (W - M - 250, y - 4), (W - M - 220, y - 4), COLOURS[name], 3)
        text(img, f"{name} ({int(s.max() - (0 if name == 'baseline' else base_end))} steps)", (W - M - 212, y), 0.45)
    cv2.imwrite(args.output, img)


def probe(args):
    report = json.load(open(args.input))
    rows = [r for r in report["rows"] if r["psnr_vs_baseline"]]
    W, M, L = 980, 60, 330
    H = 2 * M + 34 * len(rows) + 30
    lo = min(r["psnr_vs_baseline"]["lo"] for r in rows)
    hi = max(r["psnr_vs_baseline"]["hi"] for r in rows)
    pad = 0.1 * (hi - lo + 1e-9)
    lo, hi = min(lo - pad, -0.1), max(hi + pad, 0.1)
    px = lambda x: int(L + (x - lo) / (hi - lo) * (W - L - M))
    img = np.full((H, W, 3), 255, np.uint8)
    for t in nice_ticks(lo, hi):
        cv2.line(img, (px(t), M), (px(t), H - M), GREY, 1)
        text(img, f"{t:+.1f}", (px(t) - 14, H - M + 20), 0.45)
    cv2.line(img, (px(0), M), (px(0), H - M), BLACK, 1)
    steps = report["sampler"]["steps"]
    text(img, f"return-leg PSNR minus the baseline's (dB), teacher-forced, {steps} {report['sampler']['method']} steps; "
              "bars: 95% bootstrap over trajectories", (10, 30), 0.5)
    for i, r in enumerate(rows):
        y = M + 20 + 34 * i
        iv = r["psnr_vs_baseline"]
        colour = COLOURS.get(r["name"], (120, 120, 120))
        text(img, f"{r['name']}  ({r['psnr']:.2f} dB)", (10, y + 5), 0.45)
        cv2.line(img, (px(iv["lo"]), y), (px(iv["hi"]), y), colour, 2, cv2.LINE_AA)
        for x in (iv["lo"], iv["hi"]):
            cv2.line(img, (px(x), y - 6), (px(x), y + 6), colour, 2)
        cv2.circle(img, (px(iv["mean"]), y), 6, colour, -1, cv2.LINE_AA)
    cv2.imwrite(args.output, img)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("what", choices=["loss", "probe"])
    ap.add_argument("input", nargs="+", help="loss: one or more log.jsonl files; probe: one probe.json")
    ap.add_argument("-o", "--output", required=True)
    args = ap.parse_args()
    if args.what == "probe":
        if len(args.input) != 1:
            raise SystemExit("probe: give one probe.json")
        args.input = args.input[0]
    {"loss": loss, "probe": probe}[args.what](args)


if __name__ == "__main__":
    main()
