"""The model card (MODEL.md), rendered from what the trainer recorded: the
manifest (with its `lineage`, `serving` and `heldout_eval` blocks) and the
settings. Nothing in it is typed by hand."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

# Rows of the held-out eval, in the order the card shows them, and what each is.
ROWS = {
    "served_covisible": "this model, served (1 step, co-visible memory, fusion heads)",
    "started_from_covisible": "the model it was fine-tuned from, served the same way",
    "baseline": "its own 4-frame baseline (no memory), 10 DDIM steps",
    "reproject_fused": "the fused warp: the best stored frames moved into the view with their depth",
    "reproject": "the best stored frame reprojected with its depth",
}


def interval(i: dict | None, flip: bool = False) -> dict | None:
    if i is None or i["mean"] is None:
        return None  # an empty stratum
    mean, lo, hi = i["mean"], i["lo"], i["hi"]
    return {"mean": -mean, "lo": -hi, "hi": -lo} if flip else {"mean": mean, "lo": lo, "hi": hi}


def summarise(results: dict) -> dict:
    """The figures the card shows, from `worldpack eval`'s results.json. Differences are
    the served model minus each row (so positive means the served model is closer to the truth)."""
    def rows(pooled):
        return {r["row"]: {"psnr": interval(r["psnr"]), "ssim": interval(r["ssim"]),
                           "served_minus_row_db": interval(r.get("psnr_diff"), flip=True),
                           "sharpness": interval(r.get("sharpness")), "holes_psnr": interval(r.get("holes_psnr")),
                           "holes_sharpness": interval(r.get("holes_sharpness"))} for r in pooled}
    return {"suite": results["suite"], "trajectories": len(results["trajectories"]),
            "return_frames": sum(t["frames"] - t["returning_point"] for t in results["trajectories"]),
            "paired_against": results["paired_against"], "rows": rows(results["pooled"]),
            "strata": {s["name"]: {"describe": s["describe"], "frames": s["frames"], "rows": rows(s["pooled"])}
                       for s in results["strata"]}}


def fmt(i: dict | None, signed: bool = False, digits: int = 2) -> str:
    if i is None:
        return "–"
    f = f"{{:{'+' if signed else ''}.{digits}f}}"
    return f"{f.format(i['mean'])} [{f.format(i['lo'])}, {f.format(i['hi'])}]"


def table(rows: dict) -> list[str]:
    lines = ["| row | PSNR dB | served − row, dB | SSIM | sharpness | holes: PSNR | holes: sharpness |",
             "| --- | --- | --- | --- | --- | --- | --- |"]
    for name, what in ROWS.items():
        r = rows.get(name)
        if r is None:
            continue
        diff = "(the reference)" if name == "served_covisible" else fmt(r["served_minus_row_db"], signed=True)
        lines.append(f"| {what} | {fmt(r['psnr'])} | {diff} | {fmt(r['ssim'], digits=3)} | {fmt(r['sharpness'])} | "
                     f"{fmt(r['holes_psnr'])} | {fmt(r['holes_sharpness'])} |")
    return lines


def render(manifest: dict, settings: dict, lineage: dict) -> str:
    data = lineage["stages"]["check"]["data"]
    ev = manifest["heldout_eval"]
    serving = manifest["serving"]
    fam = settings["from"]
    stages = lineage["stages"]
    hours = sum(v["minutes"] for v in stages.values()) / 60
    out = [f"# {manifest['name']}", "",
           f"A WorldPack model made by `worldpack train` from `{data['suite']}` "
           f"({data['trajectories']} trajectories, {data['frames']:,} frames, 64x64, world kind `{data['kind']}`; "
           f"suite digest `{data['digest']}`).",
           "", "## Served as", "",
           f"`worldpack serve --model DIR` serves it so, with no flags: policy `{serving['policy']}`, "
           f"sampler {serving['method']} in {serving['steps']} step (a distilled student), "
           f"memory chosen by {'co-visibility' if serving['covisible'] else 'frustum overlap'}, "
           f"{serving['warp_frames']} stored frames warped into each new view.",
           "", "## Made by", "",
           ("Fine-tuned from " + ", ".join(f"{k} `{v}`" for k, v in fam.items()) if fam else "Trained from scratch") + ".",
           f"Settings: `train.json` (digest `{manifest['lineage']['settings_digest']}`); device {settings['device']}, "
           f"{settings['threads']} torch thread(s); budget {settings['hours']} h; {hours:.2f} h spent in all.", "",
           "| stage | status | minutes |", "| --- | --- | --- |"]
    out += [f"| {k} | {v['status']} | {v['minutes']:.1f} |" for k, v in stages.items() if k != "card"]
    out += ["", "## Held-out eval", "",
            f"Rollouts of the way back on {ev['trajectories']} held-out trajectories ({ev['return_frames']:,} generated "
            f"frames; `{ev['suite']}`). Means with 95% intervals resampled over trajectories; differences paired "
            "frame by frame. Sharpness: the frame's gradient energy over the truth's (1 is the truth's). Holes: "
            "where none of the warped stored frames lands.", ""]
    out += table(ev["rows"])
    for name, s in ev["strata"].items():
        if s["frames"] == 0:
            continue
        out += ["", f"**{name}** ({s['describe']}; {s['frames']:,} frames)", ""] + table(s["rows"])
    out += ["", "![a held-out way back: the truth, then each row](heldout-strip.png)", "",
            "## Limits", "",
            "- 64x64 frames; the intrinsics and world scale of the training data (positions in roughly metres).",
            "- It generates what the memory and the warp do not show from what it learned of this world: "
            "new ground is its weakest stratum.",
            "- Figures are from one held-out split of the training data's own world; a new user's scenes may differ.", ""]
    return "\n".join(out)


def report(results: Path) -> str:
    """The card's tables for one `worldpack eval` results.json: the held-out suite, then each stratum."""
    ev = summarise(json.loads(results.read_text()))
    out = [f"`{ev['suite']}`: {ev['trajectories']} walks, {ev['return_frames']:,} generated frames", ""] + table(ev["rows"])
    for name, s in ev["strata"].items():
        if s["frames"]:
            out += ["", f"{name} ({s['describe']}; {s['frames']:,} frames)", ""] + table(s["rows"])
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description="Print the model card's eval tables for results.json files of `worldpack eval`")
    ap.add_argument("results", type=Path, nargs="+")
    for path in ap.parse_args().results:
        print(report(path) + "\n")


if __name__ == "__main__":
    main()
