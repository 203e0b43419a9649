"""docs/results.md, the voxel world's results page, from `worldpack eval`
(and optionally `worldpack probe` and `worldpack study`) JSON: tables in the paper's layout (rows: methods; columns: ranges; one
table per task), per-frame PSNR curves along the return leg (PNG, OpenCV),
the commands, machine and model details.

    .venv/bin/python scripts/report.py runs/results/loopnav-test/results.json \\
        --command "./scripts/results.sh" -o docs/results.md
"""

import argparse
import json
import os
import platform
from pathlib import Path

import cv2
import numpy as np

# Row order and labels come from `worldpack eval` (results.json: rows, labels; memory::variants in Rust).
ORDER: list[str] = []
LABEL: dict[str, str] = {}
COLOURS = {"baseline": (60, 60, 60), "nearest_frame_packing": (40, 140, 40), "memory_retrieval": (200, 120, 30),
           "worldmem_greedy": (160, 60, 160), "worldpack": (30, 30, 200), "worldpack_keep_last": (0, 90, 255), "served_covisible": (0, 160, 0), "copy": (150, 150, 150), "reproject": (0, 170, 220)}
FONT = cv2.FONT_HERSHEY_SIMPLEX
# Rows no model makes (eval::evaluate's references).
REFERENCES = ("copy", "reproject", "reproject_fused", "composite")


def ordered(names):
    return sorted(names, key=lambda n: ORDER.index(n) if n in ORDER else len(ORDER))


def curves_png(results, task, path):
    curves = {c["row"]: np.array(c["psnr"]) for c in results["curves"] if c["task"] == task}
    W, H, M = 900, 480, 70
    longest = max(len(v) for v in curves.values())
    allv = np.concatenate([v for v in curves.values()])
    y0, y1 = np.floor(np.nanmin(allv)) - 1, np.ceil(np.nanmax(allv)) + 1
    px = lambda x, y: (int(M + x / max(longest - 1, 1) * (W - 2 * M)), int(H - M - (y - y0) / (y1 - y0) * (H - 2 * M)))
    img = np.full((H, W, 3), 255, np.uint8)
    for y in range(int(y0), int(y1) + 1, 2):
        cv2.line(img, px(0, y), px(longest - 1, y), (225, 225, 225), 1)
        cv2.putText(img, f"{y}", (20, px(0, y)[1] + 5), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    step = next(s for s in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 10**9) if longest / s <= 10)
    for x in range(0, longest, step):
        cv2.putText(img, f"{x}", (px(x, y0)[0] - 10, H - M + 20), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.rectangle(img, (M, M), (W - M, H - M), (0, 0, 0), 1)
    cv2.putText(img, f"{task.upper()}: PSNR (dB) along the generated return leg, mean over trajectories; x: frames generated",
                (M, 35), FONT, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for i, name in enumerate(ordered(curves)):
        v = curves[name]
        k = max(1, len(v) // 60)  # light smoothing so the lines stay readable
        sm = np.convolve(np.nan_to_num(v, nan=np.nanmean(v)), np.ones(k) / k, mode="valid")
        pts = np.array([px(j + k - 1, y) for j, y in enumerate(sm)], np.int32)
        colour = COLOURS.get(name, (0, 0, 0))
        cv2.polylines(img, [pts], False, colour, 2, cv2.LINE_AA)
        y = M + 18 + 20 * i
        cv2.line(img, (W - M - 230, y - 4), (W - M - 200, y - 4), colour, 3)
        cv2.putText(img, LABEL.get(name, name).strip("*"), (W - M - 192, y), FONT, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def paired_interval(results, row, metric):
    """Row − the reference row (`paired_against`, normally the baseline) over
    every generated frame, with its 95% interval over trajectories, as
    `worldpack eval` computed it (eval::stats::pooled); None when absent."""
    entry = next((p for p in results.get("pooled", []) if p["row"] == row), None)
    diff = entry and entry.get(f"{metric}_diff")
    return (diff["mean"], diff["lo"], diff["hi"]) if diff else None


def fmt(v, sign=""):
    """`mean [lo, hi]` of an interval `worldpack eval` computed, or a dash; `sign="+"` for differences."""
    if not v or v.get("mean") is None:
        return "—"
    if v.get("lo") is None or v.get("hi") is None:
        return f"{v['mean']:{sign}.2f}"
    return f"{v['mean']:{sign}.2f} [{v['lo']:{sign}.2f}, {v['hi']:{sign}.2f}]"


def strata_section(res, rows):
    """Revisits and new ground, and the warp's holes, per row: where memory has
    pixels and where it has none (eval::strata, eval::metrics)."""
    strata = res.get("strata", [])
    if not strata:
        return []
    lines = ["", "## Where memory has pixels and where it has none", "",
             "PSNR (dB) and the sharpness ratio (the frame's edge energy over the truth's; 1 is as sharp as the truth) over "
             "each stratum's frames, and over the pixels where the exploration's fused warp does not land (*holes*); "
             "95% bootstrap intervals over trajectories, differences paired against the baseline. The references leave "
             "the warp's holes black, so their edges count as edge energy: a ratio above 1 there is not detail.", ""]
    for st in strata:
        lines += [f"**{st['name'].replace('_', ' ')}** ({st['describe']}): {st['frames']} frames of {st['trajectories']} trajectories.", "",
                  "| row | PSNR | Δ PSNR | sharpness | holes: PSNR | holes: sharpness |", "|---|---|---|---|---|---|"]
        pooled = {p["row"]: p for p in st["pooled"]}
        for row in rows:
            p = pooled.get(row)
            if p is None:
                continue
            lines.append(f"| {LABEL.get(row, row)} | {fmt(p.get('psnr'))} | {fmt(p.get('psnr_diff'), '+')} | {fmt(p.get('sharpness'))} | "
                         f"{fmt(p.get('holes_psnr'))} | {fmt(p.get('holes_sharpness'))} |")
        lines.append("")
    return lines


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("results")
    ap.add_argument("--probe", help="JSON from `worldpack probe --out`")
    ap.add_argument("--study", help="study.json from `worldpack study` (speed/accuracy chart, pose noise, failure strata)")
    ap.add_argument("--command", default="./scripts/results.sh", help="the command that produced the inputs, quoted in the report")
    ap.add_argument("-o", "--output", required=True)
    a = ap.parse_args()
    res = json.loads(Path(a.results).read_text())
    ORDER[:] = [r["name"] for r in res.get("rows", [])]
    LABEL.update(res.get("labels", {}))
    # The row results.sh adds: `worldpack eval` labels an extra row by its name.
    if LABEL.get("served_covisible", "served_covisible") == "served_covisible":
        LABEL["served_covisible"] = "Served model (1-step, co-visible)"
    if "worldpack" in LABEL:  # the paper's method stands out in the tables
        LABEL["worldpack"] = f"**{LABEL['worldpack']}**"
    out = Path(a.output)
    pictures = out.parent / "results"
    pictures.mkdir(parents=True, exist_ok=True)
    cells = res["cells"]
    tasks = sorted({c["task"] for c in cells})
    ranges = sorted({c["range"] for c in cells})
    rows = ordered({c["row"] for c in cells})
    cell = {(c["task"], c["range"], c["row"]): c for c in cells}
    n_traj = len(res["trajectories"])
    per_cell = max(c["trajectories"] for c in cells)
    lines = ["# Results: the voxel world", "",
             "What the paper's pair (`worldpack eval --policies baseline,worldpack`) and the served model do today on "
             "LoopNav-style rollouts. Doom's page is [doom.md](doom.md#results); how the figures moved over time is in "
             "[changelog.md](changelog.md).", "",
             f"Generated by `{a.command}` (which runs `worldpack eval` and `scripts/report.py`); do not edit by hand.", "",
             f"- Suite: `{res['suite']}`, {n_traj} trajectories (up to {per_cell} per task and range), test world seeds.",
             f"- Models: `{res['models']}`; policies run with the weights {json.dumps(res['weights'])}.",
             "- Rows: " + ", ".join(f"{r['name']} `{r['model'].split(' #')[0]}`" for r in res.get("rows", []) if r.get("model")) + ".",
             f"- Sampler: {res['sampler']['steps']} {res['sampler']['method']} steps per frame; "
             f"return legs {'capped at ' + str(res['max_frames']) + ' frames' if res['max_frames'] else 'generated in full'}.",
             f"- Machine: {platform.machine()}, {os.cpu_count()} cores, {platform.system()}; CPU execution provider.",
             "- Protocol: every trajectory's exploration (look-around and outbound legs) is observed as ground truth; the return leg "
             "is generated frame by frame from the true poses and actions, each generated frame joining the memory. "
             "The references copy or depth-warp the observed frame of largest overlap with the target view.", ""]
    wall = {r["name"]: r["wall_s"] for r in res["rows"]}
    per_task = {(t["task"], t["row"]): t for t in res.get("tasks", [])}
    for task in tasks:
        lines += [f"## {task.upper()}", "", "PSNR (dB) / SSIM, mean ± std over trajectories of each trajectory's mean.", "",
                  "| method | " + " | ".join(f"range {r}" for r in ranges) + " | all ranges |",
                  "|---|" + "---|" * (len(ranges) + 1)]
        for row in rows:
            vals = []
            for r in ranges:
                c = cell.get((task, r, row))
                vals.append(f"{c['psnr'][0]:.2f} ± {c['psnr'][1]:.2f} / {c['ssim'][0]:.3f}" if c else "—")
            t = per_task.get((task, row))
            vals.append(f"{t['psnr']:.2f} / {t['ssim']:.3f}" if t else "—")
            lines.append(f"| {LABEL.get(row, row)} | " + " | ".join(vals) + " |")
        fvd = {(c["task"], c["range"], row): c for row, cs in res.get("fvd", {}).items() for c in cs}
        if any("lpips" in cell.get((task, r, row), {}) or "dreamsim" in cell.get((task, r, row), {}) or (task, r, row) in fvd
               for r in ranges for row in rows):
            lines += ["", "Learned metrics, feature networks " + json.dumps(res.get("feature_networks")) +
                      ": LPIPS / DreamSim distance (lower is better) / FVD [95% bootstrap over clips].", "",
                      "| method | " + " | ".join(f"range {r}" for r in ranges) + " |", "|---|" + "---|" * len(ranges)]
            for row in rows:
                vals = []
                for r in ranges:
                    c, f = cell.get((task, r, row), {}), fvd.get((task, r, row))
                    parts = [f"{c[k][0]:.4f}" if k in c else "—" for k in ("lpips", "dreamsim")]
                    parts.append(f"{f['fvd']:.3g} [{f['lo']:.3g}, {f['hi']:.3g}]" if f else "—")
                    vals.append(" / ".join(parts))
                lines.append(f"| {LABEL.get(row, row)} | " + " | ".join(vals) + " |")
        png = pictures / f"curves-{task}.png"
        curves_png(res, task, png)
        lines += ["", f"![{task} per-frame PSNR]({png.relative_to(out.parent)})", ""]

    # The ordering, stated from the numbers rather than assumed.
    pooled = {}
    for row in rows:
        xs = [(cell[(t, r, row)]["psnr"][0], cell[(t, r, row)]["trajectories"]) for t in tasks for r in ranges if (t, r, row) in cell]
        pooled[row] = sum(v * n for v, n in xs) / max(sum(n for _, n in xs), 1)
    ranking = sorted(pooled, key=lambda r: -pooled[r])
    lines += ["## Ordering", "", "Pooled return-leg PSNR over every task and range, best first: " +
              ", ".join(f"{LABEL.get(r, r)} {pooled[r]:.2f}" for r in ranking) + ".", ""]
    learned = [r for r in ranking if r not in REFERENCES]
    if "worldpack" in pooled and "baseline" in pooled:
        d = pooled["worldpack"] - pooled["baseline"]
        line = (f"The paper orders WorldPack first and the 4-frame baseline last among the learned methods. Here WorldPack is "
                f"{learned.index('worldpack') + 1} of {len(learned)} learned methods, {d:+.2f} dB from the baseline")
        per_frame = res.get("per_frame", {})
        if res.get("paired_against") == "baseline" and paired_interval(res, "worldpack", "psnr"):
            m, lo, hi = paired_interval(res, "worldpack", "psnr")
            verdict = "above zero" if lo > 0 else "below zero" if hi < 0 else "spanning zero: these rollouts do not separate it from the baseline"
            line += f"; frame-weighted and paired, {m:+.2f} dB with a 95% interval of [{lo:+.2f}, {hi:+.2f}], {verdict}"
        lines.append(line + ".")
    per_frame = res.get("per_frame", {})
    if res.get("paired_against") == "baseline":
        lines += ["", "Paired differences to the baseline over every generated frame (95% bootstrap intervals over trajectories):", "",
                  "| method | ΔPSNR (dB) | ΔSSIM |", "|---|---|---|"]
        for row in rows:
            if row == "baseline" or paired_interval(res, row, "psnr") is None:
                continue
            p, s_ = paired_interval(res, row, "psnr"), paired_interval(res, row, "ssim")
            lines.append(f"| {LABEL.get(row, row)} | {p[0]:+.2f} [{p[1]:+.2f}, {p[2]:+.2f}] | {s_[0]:+.3f} [{s_[1]:+.3f}, {s_[2]:+.3f}] |")
    lines += strata_section(res, rows)
    total = sum(wall.values())
    frames = sum(len(t) for t in next(iter(per_frame.values()), []))
    lines += ["", "Time per row (whole suite): " + ", ".join(f"{r} {wall[r]:.0f} s" for r in ordered(wall)) +
              f"; {total / 60:.1f} min in all for {frames} generated frames per row. Rows scale with the frames generated, so "
              f"LoopNav's 18 trajectories per cell (144) would take about {total / 60 * 144 / max(n_traj, 1):.0f} min on the same machine "
              "(an estimate, not a run).", ""]

    if a.probe:
        p = json.loads(Path(a.probe).read_text())
        lines += ["## Memory probe (teacher-forced, docs/probe.md)", "",
                  f"One-step prediction of every return-leg frame from ground-truth history; {p['sampler']['steps']} "
                  f"{p['sampler']['method']} steps; 95% intervals from {p['bootstrap']['reps']} bootstrap resamples of trajectories.", "",
                  "| row | frames | PSNR | SSIM | ΔPSNR vs baseline [95% CI] | ms/frame |", "|---|---|---|---|---|---|"]
        for r in p["rows"]:
            iv = r["psnr_vs_baseline"]
            ci = f"{iv['mean']:+.2f} [{iv['lo']:+.2f}, {iv['hi']:+.2f}]" if iv else "—"
            lines.append(f"| {r['name']} | {r['frames']} | {r['psnr']:.2f} | {r['ssim']:.3f} | {ci} | {r['latency_ms']:.1f} |")
        lines.append("")
    if a.study:
        from study_report import markdown as study_markdown

        lines += study_markdown(json.loads(Path(a.study).read_text()), pictures, os.path.relpath(pictures, out.parent))
    out.write_text("\n".join(lines) + "\n")
    print(f"wrote {out} and {pictures}/")


if __name__ == "__main__":
    main()
