"""The `worldpack study` part of docs/results.md: the speed/accuracy chart
(PNG and SVG from one list of drawing commands), the recommended default,
the pose-noise tables and the failure strata. Imported by report.py.

    .venv/bin/python scripts/study_report.py runs/study/study.json   # prints the markdown, writes the chart
"""

import json
import math
import sys
from pathlib import Path
from xml.sax.saxutils import escape

import cv2
import numpy as np

GROUP_COLOUR = {  # RGB
    "policy": (40, 80, 200), "keep_last": (0, 150, 255), "steps": (200, 60, 40), "estimator": (150, 60, 170),
    "far": (40, 150, 60), "size": (210, 140, 20), "reference": (90, 90, 90),
}
GROUP_LABEL = {
    "policy": "context policy (own weights, 10 steps)", "keep_last": "WorldPack, newest frame kept", "steps": "WorldPack, sampler steps",
    "estimator": "WorldPack, Monte Carlo overlap", "far": "WorldPack, frustum far", "size": "other models (--extra)", "reference": "non-learned reference",
}
# Point labels come from `worldpack study` (study.json: labels; memory::short_label in Rust).
LABELS: dict[str, str] = {}


def short(name):
    return LABELS.get(name, name)


class Canvas:
    """Records drawing commands in pixel coordinates; renders them as PNG (OpenCV) or SVG."""

    def __init__(self, w, h):
        self.w, self.h, self.ops = w, h, []

    def line(self, a, b, rgb, width=1, dash=False):
        self.ops.append(("line", a, b, rgb, width, dash))

    def circle(self, c, r, rgb, fill=True):
        self.ops.append(("circle", c, r, rgb, fill))

    def text(self, p, s, size=12, rgb=(0, 0, 0), anchor="start"):
        self.ops.append(("text", p, s, size, rgb, anchor))

    def png(self, path):
        img = np.full((self.h, self.w, 3), 255, np.uint8)
        bgr = lambda c: (c[2], c[1], c[0])
        for op in self.ops:
            if op[0] == "line":
                _, a, b, c, w, dash = op
                if dash:
                    n = max(1, int(math.dist(a, b) / 6))
                    for i in range(0, n, 2):
                        p = (int(a[0] + (b[0] - a[0]) * i / n), int(a[1] + (b[1] - a[1]) * i / n))
                        q = (int(a[0] + (b[0] - a[0]) * (i + 1) / n), int(a[1] + (b[1] - a[1]) * (i + 1) / n))
                        cv2.line(img, p, q, bgr(c), w, cv2.LINE_AA)
                else:
                    cv2.line(img, tuple(map(int, a)), tuple(map(int, b)), bgr(c), w, cv2.LINE_AA)
            elif op[0] == "circle":
                _, c, r, col, fill = op
                cv2.circle(img, tuple(map(int, c)), int(r), bgr(col), -1 if fill else 2, cv2.LINE_AA)
            else:
                _, p, s, size, col, anchor = op
                scale = size / 30.0
                (tw, _), _ = cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
                x = p[0] - tw if anchor == "end" else p[0] - tw // 2 if anchor == "middle" else p[0]
                cv2.putText(img, s, (int(x), int(p[1])), cv2.FONT_HERSHEY_SIMPLEX, scale, bgr(col), 1, cv2.LINE_AA)
        cv2.imwrite(str(path), img)

    def svg(self, path):
        rgb = lambda c: f"rgb({c[0]},{c[1]},{c[2]})"
        out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{self.w}" height="{self.h}" viewBox="0 0 {self.w} {self.h}" '
               'font-family="Helvetica, Arial, sans-serif">', f'<rect width="{self.w}" height="{self.h}" fill="white"/>']
        for op in self.ops:
            if op[0] == "line":
                _, a, b, c, w, dash = op
                d = ' stroke-dasharray="6 6"' if dash else ""
                out.append(f'<line x1="{a[0]:.1f}" y1="{a[1]:.1f}" x2="{b[0]:.1f}" y2="{b[1]:.1f}" stroke="{rgb(c)}" stroke-width="{w}"{d}/>')
            elif op[0] == "circle":
                _, c, r, col, fill = op
                paint = f'fill="{rgb(col)}"' if fill else f'fill="none" stroke="{rgb(col)}" stroke-width="2"'
                out.append(f'<circle cx="{c[0]:.1f}" cy="{c[1]:.1f}" r="{r}" {paint}/>')
            else:
                _, p, s, size, col, anchor = op
                out.append(f'<text x="{p[0]:.1f}" y="{p[1]:.1f}" font-size="{size}" fill="{rgb(col)}" text-anchor="{anchor}">{escape(s)}</text>')
        out.append("</svg>")
        Path(path).write_text("\n".join(out) + "\n")


def on_front(points, flag):
    """Indices of the points study.json marks on a front (`pareto` or `pareto_learned`), fastest first."""
    return sorted((i for i, p in enumerate(points) if p[flag]), key=lambda i: points[i]["latency_ms"])


def recommended(study):
    """The recommended point and the most accurate learned one, as `worldpack study` chose them."""
    by_name = {p["name"]: p for p in study["tradeoff"]}
    r = study["recommended"]
    return by_name[r["name"]], by_name[r["best"]]


def chart(study, png, svg):
    pts = study["tradeoff"]
    W, H, L, R, T, B = 1010, 680, 80, 270, 50, 60
    c = Canvas(W, H)
    lat = [p["latency_ms"] for p in pts]
    x0, x1 = math.floor(math.log10(min(lat))), math.ceil(math.log10(max(lat)))
    psnr = [p["psnr"] for p in pts]
    y0, y1 = math.floor(min(psnr) - 0.3), math.ceil(max(psnr) + 0.3)
    px = lambda ms, db: (L + (math.log10(ms) - x0) / (x1 - x0) * (W - L - R), H - B - (db - y0) / (y1 - y0) * (H - T - B))
    for e in range(x0, x1 + 1):
        for m in (1, 2, 5):
            v = m * 10 ** e
            if v > 10 ** x1:
                continue
            x = px(v, y0)[0]
            c.line((x, T), (x, H - B), (230, 230, 230))
            c.text((x, H - B + 18), f"{v:g}", 11, anchor="middle")
    for y in range(y0, y1 + 1):
        yy = px(10 ** x0, y)[1]
        c.line((L, yy), (W - R, yy), (230, 230, 230))
        c.text((L - 8, yy + 4), f"{y}", 11, anchor="end")
    c.line((L, H - B), (W - R, H - B), (0, 0, 0))
    c.line((L, T), (L, H - B), (0, 0, 0))
    c.text((L + (W - L - R) / 2, H - 15), "milliseconds per predicted frame, batch 1, one CPU thread (log scale)", 12, anchor="middle")
    c.text((12, T - 20), f"Return-leg PSNR (dB), teacher-forced, {study['targets']} targets over {study['trajectories']} trajectories", 13)
    for idx, dash in ((on_front(pts, "pareto"), False), (on_front(pts, "pareto_learned"), True)):
        line = [px(pts[i]["latency_ms"], pts[i]["psnr"]) for i in idx]
        for a, b in zip(line, line[1:]):
            c.line(a, (b[0], a[1]), (120, 120, 120), 1, dash)
            c.line((b[0], a[1]), b, (120, 120, 120), 1, dash)
    rec, _ = recommended(study)
    # Labels go where they hit no other label or point and stay inside the plot.
    taken = [(q[0] - 6, q[1] - 6, q[0] + 6, q[1] + 6) for q in (px(p["latency_ms"], p["psnr"]) for p in pts)]
    offsets = [(8, -6, "start"), (8, 12, "start"), (-8, -6, "end"), (-8, 12, "end"), (8, -18, "start"), (-8, -18, "end"),
               (8, 24, "start"), (-8, 24, "end"), (8, -30, "start"), (-8, -30, "end")]
    for p in pts:
        q = px(p["latency_ms"], p["psnr"])
        col = GROUP_COLOUR.get(p["group"], (0, 0, 0))
        c.circle(q, 5, col)
        if p is rec:
            c.circle(q, 10, (220, 0, 0), fill=False)
        label = short(p["name"])
        width = 7.2 * len(label)
        for dx, dy, anchor in offsets:
            left = q[0] + dx if anchor == "start" else q[0] + dx - width
            box = (left, q[1] + dy - 10, left + width, q[1] + dy + 2)
            inside = box[0] >= L and box[2] <= W - R and box[1] >= T
            if inside and not any(box[0] < b[2] and b[0] < box[2] and box[1] < b[3] and b[1] < box[3] for b in taken):
                break
        else:
            dx, dy, anchor = offsets[0]
            box = (q[0] + dx, q[1] + dy - 10, q[0] + dx + width, q[1] + dy + 2)
        taken.append(box)
        c.text((q[0] + dx, q[1] + dy), label, 10, col, anchor)
    y = T + 10
    for g, label in GROUP_LABEL.items():
        if any(p["group"] == g for p in pts):
            c.circle((W - R + 40, y - 4), 5, GROUP_COLOUR[g])
            c.text((W - R + 52, y), label, 11)
            y += 20
    c.line((W - R + 32, y - 4), (W - R + 48, y - 4), (120, 120, 120))
    c.text((W - R + 52, y), "Pareto front, all points", 11)
    c.line((W - R + 32, y + 16), (W - R + 48, y + 16), (120, 120, 120), 1, True)
    c.text((W - R + 52, y + 20), "Pareto front, learned only", 11)
    c.circle((W - R + 40, y + 36), 9, (220, 0, 0), fill=False)
    c.text((W - R + 52, y + 40), "recommended default", 11)
    c.png(png)
    c.svg(svg)


def iv(i):
    return f"{i['mean']:+.2f} [{i['lo']:+.2f}, {i['hi']:+.2f}]"


def markdown(study, pictures, rel):
    """Markdown lines for docs/results.md; writes the chart into `pictures` (linked as `rel`)."""
    LABELS.update(study.get("labels", {}))
    chart(study, pictures / "tradeoff.png", pictures / "tradeoff.svg")
    pts = study["tradeoff"]
    rec, best = recommended(study)
    lines = ["## Speed against accuracy", "",
             f"Every point is the teacher-forced probe (docs/probe.md) on the same {study['targets']} return-leg targets "
             f"(every {study['stride']}th frame of {study['trajectories']} trajectories), {study['sampler']['steps']} "
             f"{study['sampler']['method']} steps unless the row says otherwise, against the median time of one batch-1 prediction "
             "(selection, packing, sampling and decoding; 20 timed after 3 untimed, one intra-op thread, which was both faster and "
             "steadier than two on this 2-core CPU).", "",
             f"![speed against accuracy]({rel}/tradeoff.png) ([SVG]({rel}/tradeoff.svg))", "",
             "| configuration | what varies | ms/frame | PSNR | SSIM | ΔPSNR vs baseline [95%] | on the front |", "|---|---|---|---|---|---|---|"]
    for p in sorted(pts, key=lambda p: p["latency_ms"]):
        mark = "all" if p["pareto"] else "learned" if p["pareto_learned"] else ""
        params = f", {p['parameters'] / 1e6:.2f} M" if p.get("parameters") else ""
        lines.append(f"| {short(p['name'])}{params} | {p['group'].replace('_', ' ')} | {p['latency_ms']:.2f} | {p['psnr']:.2f} | {p['ssim']:.3f} | "
                     f"{iv(p['psnr_vs_baseline']) if p['name'] != 'baseline' else '—'} | {mark} |")
    why = ("It is the most accurate learned configuration and sits on the learned front: nothing learned is faster at its accuracy, "
           "and everything learned that is faster is clearly less accurate (the table's intervals)." if rec is best else
           f"It is the fastest learned configuration on the learned front whose interval against the baseline overlaps that of the most "
           f"accurate learned configuration ({short(best['name'])}, {best['psnr']:.2f} dB, {best['latency_ms']:.1f} ms/frame): the "
           "measurements cannot tell it from the best, and nothing learned is faster at its accuracy.")
    lines += ["", f"**Recommended default: {short(rec['name'])}** ({rec['latency_ms']:.1f} ms/frame, {rec['psnr']:.2f} dB). " + why]
    if rec.get("steps") and rec["steps"] < study["sampler"]["steps"]:
        lines += ["", f"A caution on fewer steps: PSNR and SSIM reward the smoother frames a short DDIM schedule makes, so "
                  f"{rec['steps']} steps can score above {study['sampler']['steps']} while looking blurrier; too few steps "
                  "(see the 2-step rows) break down entirely. A perceptual metric would weigh sharpness, but none of the "
                  "feature networks can be downloaded here ([metrics.md](metrics.md))."]
    refs = [p for p in pts if p["pareto"] and p["group"] == "reference"]
    if refs:
        lines += ["", "On the front of all points the non-learned references " + " and ".join(short(r["name"]) for r in refs) +
                  " sit ahead of every model: at 64×64 with true poses, warping a stored frame with its depth is both faster and "
                  "closer than anything trained here. The model earns its cost where the poses are not to be trusted (next section: "
                  "under every level of independent pose noise the warp loses more than any model) or where no stored frame shows "
                  "the view (the memory-dependent stratum below)."]
    lines.append("")

    lines += ["## Stability under pose noise", "",
              "The frames are true; the poses the system believes are not. Selection, the model's relative-pose conditioning and the "
              "depth warp all see the believed poses. *Independent*: each frame's position gets N(0, σ²) per axis and its orientation a "
              "rotation vector with N(0, σ²) components. *Drift*: each step's motion is measured with that error and chained, as dead "
              "reckoning does. *OpenCV visual odometry*: poses estimated from 224×224 renders of the same trajectories "
              "(ORB, ratio test, `solvePnPRansac` with the previous frame's depth), chained from the true first pose "
              "(`scripts/visual_odometry.py`). Frame 0 is always known.", "",
              "One-step quality (the teacher-forced probe): ΔPSNR of each row against the same row with true poses, paired per frame, "
              "95% interval over trajectories.", ""]
    rows = [r["row"] for r in study["noise"][0]["rows"]] if study["noise"] else []
    lines += ["| condition | pose error (blocks / °) | " + " | ".join(short(r) for r in rows) + " |", "|---|---|" + "---|" * len(rows)]
    for c in study["noise"]:
        cells = {r["row"]: r for r in c["rows"]}
        lines.append(f"| {c['condition']} | {c['pose_error_blocks']:.2f} / {c['pose_error_deg']:.1f} | " +
                     " | ".join(iv(cells[r]["psnr_vs_clean"]) for r in rows) + " |")
    if study.get("rollouts"):
        clean = next(c for c in study["rollouts"] if c["condition"] == "clean")
        rrows = [r["row"] for r in clean["rows"]]
        lines += ["", f"Rollouts under the same noise: the first {study['rollout_frames']} frames of every return leg generated "
                  "autoregressively (each generated frame joins the memory with its believed pose), so a wrong pose can compound. "
                  "ΔPSNR against the same row's noise-free rollout, paired per frame, 95% interval over trajectories.", "",
                  "| condition | frames per row | " + " | ".join(short(r) for r in rrows) + " |", "|---|---|" + "---|" * len(rrows)]
        for c in study["rollouts"]:
            cells = {r["row"]: r for r in c["rows"]}
            vals = [f"{cells[r]['psnr']:.2f} dB" if cells[r]["psnr_vs_clean"] is None else iv(cells[r]["psnr_vs_clean"]) for r in rrows]
            lines.append(f"| {c['condition']} | {c['frames']} | " + " | ".join(vals) + " |")
    pol = [s["policy"] for s in study["noise"][0]["selection"]] if study["noise"] else []
    lines += ["", "Selection stability: mean Jaccard overlap of the selected frames with the noise-free selection, and mean Spearman "
              "ρ of their ranks (a frame one plan left out counts as tied last there), over the same targets.", "",
              "| condition | " + " | ".join(short(p) for p in pol) + " |", "|---|" + "---|" * len(pol)]
    for c in study["noise"]:
        s = {x["policy"]: x for x in c["selection"]}
        lines.append(f"| {c['condition']} | " + " | ".join(f"{s[p]['jaccard']:.2f} / {s[p]['rank']:.2f}" for p in pol) + " |")
    lines.append("")

    lines += ["## Where methods fail", "",
              "Return-leg targets grouped by what makes them hard for a geometric memory, from true poses and depth only; "
              "the thresholds were fixed from the feature distributions before any model was scored (`eval::strata`). "
              "Noise-free; ΔPSNR against the baseline on the same targets, 95% interval over trajectories.", ""]
    srows = [r["row"] for r in study["strata"][0]["rows"]]
    lines += ["| stratum | targets (trajectories) | " + " | ".join(short(r) for r in srows) + " |", "|---|---|" + "---|" * len(srows)]
    for st in study["strata"]:
        cells = {r["row"]: r for r in st["rows"]}
        vals = []
        for r in srows:
            x = cells[r]
            if st["targets"] == 0:
                vals.append("—")
            elif x["psnr_vs_baseline"] is None:
                vals.append(f"{x['psnr']:.2f} dB")
            else:
                vals.append(iv(x["psnr_vs_baseline"]))
        lines.append(f"| {st['stratum'].replace('_', ' ')}: {st['description']} | {st['targets']} ({st['trajectories']}) | " + " | ".join(vals) + " |")
    lines.append("")

    # The paper's control for geometric selection: the same packing filled by recency.
    grows = [r["row"] for r in study["strata"][0]["rows"] if r.get("psnr_vs_recency")]
    if grows:
        lines += ["Against Nearest Frame Packing instead, which packs the same 22-frame budget by recency (the paper's control for "
                  "geometric selection): ΔPSNR on the same targets, 95% interval over trajectories. An interval above zero on "
                  "memory-dependent targets is the memory effect beyond recency.", "",
                  "| stratum | " + " | ".join(short(r) for r in grows) + " |", "|---|" + "---|" * len(grows)]
        for st in study["strata"]:
            cells = {r["row"]: r for r in st["rows"]}
            vals = [iv(cells[r]["psnr_vs_recency"]) if st["targets"] and cells[r].get("psnr_vs_recency") else "—" for r in grows]
            lines.append(f"| {st['stratum'].replace('_', ' ')} ({st['targets']}) | " + " | ".join(vals) + " |")
        lines.append("")
    return lines


if __name__ == "__main__":
    study = json.loads(Path(sys.argv[1]).read_text())
    out = Path(sys.argv[2]) if len(sys.argv) > 2 else Path("docs/results")
    out.mkdir(parents=True, exist_ok=True)
    print("\n".join(markdown(study, out, out.name)))
