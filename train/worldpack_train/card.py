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
    "worldpack": "the paper's WorldPack (packed memory, no warp input), 10 DDIM steps",
    "baseline": "its own 4-frame baseline (no memory), 10 DDIM steps",
    "reproject_fused": "the fused warp: the best stored frames moved into the view with their depth",
    "reproject": "the best stored frame reprojected with its depth",
}

# How to read the eval tables, under each card's heading.
READING = ("Means with 95% intervals resampled over walks; differences paired frame by frame. Sharpness: the "
           "frame's gradient energy over the truth's (1 is the truth's). Holes: where none of the warped stored "
           "frames lands.")


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
                           "served_minus_row_holes_db": interval(r.get("holes_psnr_diff"), flip=True),
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
    # Rounded first (+ 0.0 drops a negative zero), so that -0.001 reads +0.00, not -0.00.
    g = lambda x: f.format(round(x, digits) + 0.0)
    return f"{g(i['mean'])} [{g(i['lo'])}, {g(i['hi'])}]"


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
           "", "## Served as", "", *served_as(serving),
           "", "## Made by", "",
           ("Fine-tuned from " + ", ".join(f"{k} `{v}`" for k, v in fam.items()) if fam else "Trained from scratch") + ".",
           f"Settings: `train.json` (digest `{manifest['lineage']['settings_digest']}`); device {settings['device']}, "
           f"{settings['threads']} torch thread(s); budget {settings['hours']} h; {hours:.2f} h spent in all.", "",
           "| stage | status | minutes |", "| --- | --- | --- |"]
    out += [f"| {k} | {v['status']} | {v['minutes']:.1f} |" for k, v in stages.items() if k != "card"]
    out += ["", "## Held-out eval", "",
            f"Rollouts of the way back on {ev['trajectories']} held-out trajectories ({ev['return_frames']:,} generated "
            f"frames; `{ev['suite']}`). {READING}", ""]
    out += eval_tables(ev)
    out += ["", "![a held-out way back: the truth, then each row](heldout-strip.png)", "",
            "## Limits", "",
            sizes(manifest["image"]),
            "- The intrinsics and world scale of the training data (positions in roughly metres).",
            "- It generates what the memory and the warp do not show from what it learned of this world: "
            "new ground is its weakest stratum.",
            "- Figures are from one held-out split of the training data's own world; a new user's scenes may differ.", ""]
    return "\n".join(out)


def sizes(image: dict) -> str:
    """The card's line on frame sizes: the model's own, and a session's (model::full_size)."""
    return (f"- Frames: it sees and makes {image['width']}x{image['height']}; a session keeps its frames at their own size "
            "(up to `serve --max-frame-side`, 512) and is answered at it, its stored frames shown where they land and this "
            "model's frame brought up elsewhere ([fullsize.md](../../../docs/fullsize.md)).")


def served_as(serving: dict) -> list[str]:
    return [f"`worldpack serve --model DIR` serves it so, with no flags: policy `{serving['policy']}`, "
            f"sampler {serving['method']} in {serving['steps']} step{'s' if serving['steps'] > 1 else ' (a distilled student)'}, "
            f"memory chosen by {'co-visibility' if serving['covisible'] else 'frustum overlap'}, "
            f"{serving['warp_frames']} stored frames warped into each new view."]


def eval_tables(ev: dict) -> list[str]:
    out = table(ev["rows"])
    for name, s in ev["strata"].items():
        if s["frames"]:
            out += ["", f"**{name}** ({s['describe']}; {s['frames']:,} frames)", ""] + table(s["rows"])
    return out


def render_shipped(manifest: dict, world: str) -> str:
    """The card of a shipped model the recipe's stages made one by one (before the trainer):
    its last stage's training block, how it is served, and its test-suite eval."""
    t, ev = manifest["training"], manifest["heldout_eval"]
    data = t["data"]
    maps = f", maps {', '.join(data['maps'])}" if data.get("maps") else ""
    out = [f"# {manifest['name']} ({world})", "",
           f"The served {world} model: WorldPack with the warp input, distilled to one denoiser call, with a fusion "
           "head after the decoder. It was made by the recipe's stages run one at a time, before `worldpack train` "
           f"existed; `worldpack train --from {world.lower()}` now fine-tunes this family on new data in one command "
           "([training.md](../../../docs/training.md)).", "",
           "## Served as", "", *served_as(manifest["serving"]), "",
           "## Trained on", "",
           f"Its last stage: `{data['suite']}` ({data['trajectories']} walks, split `{data['split']}`, "
           f"{data['frame_size'][0]}x{data['frame_size'][1]}{maps}); policy `{t['policy']}`, {t['steps']:,} steps, "
           f"{t['weights']} weights; recipe: " + ", ".join(f"{k} {v}" for k, v in t["recipe"].items()) + ".", "",
           "## Test-suite eval", "",
           f"Rollouts of the way back on {ev['trajectories']} walks of `{ev['suite']}` never trained on "
           f"({ev['return_frames']:,} generated frames), made by `{ev['command']}`. {READING}", ""]
    out += eval_tables(ev)
    out += ["", "## Limits", "",
            sizes(manifest["image"]),
            "- The intrinsics and scale of its world (positions in roughly metres).",
            "- Where the memory has no pixels (new ground, holes) its detail is what it learned of its world.", ""]
    return "\n".join(out)


def ship(model: Path, figures: Path, world: str) -> None:
    """Writes a shipped model's test-suite eval (a saved `scripts/figures.py` summary) into
    its manifest as `heldout_eval`, then its MODEL.md from the manifest."""
    manifest = json.loads((model / "manifest.json").read_text())
    manifest["heldout_eval"] = json.loads(figures.read_text())
    (model / "manifest.json").write_text(json.dumps(manifest, indent=2) + "\n")
    (model / "MODEL.md").write_text(render_shipped(manifest, world))
    print(f"wrote {model / 'MODEL.md'} and the manifest's heldout_eval")


def report(results: Path) -> str:
    """The card's tables for one `worldpack eval` results.json: the held-out suite, then each stratum."""
    ev = summarise(json.loads(results.read_text()))
    out = [f"`{ev['suite']}`: {ev['trajectories']} walks, {ev['return_frames']:,} generated frames", ""] + eval_tables(ev)
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description="Print the model card's eval tables for results.json files of "
                                 "`worldpack eval`, or (--ship) write a shipped model's card")
    ap.add_argument("results", type=Path, nargs="*")
    ap.add_argument("--ship", type=Path, help="a shipped model folder: its card from --eval's saved summary")
    ap.add_argument("--eval", type=Path, help="with --ship: docs/figures/NAME.json of its test suite")
    ap.add_argument("--world", help="with --ship: the world's name on the card")
    a = ap.parse_args()
    if a.ship:
        if not (a.eval and a.world):
            raise SystemExit("--ship needs --eval and --world")
        ship(a.ship, a.eval, a.world)
    for path in a.results:
        print(report(path) + "\n")


if __name__ == "__main__":
    main()
