"""The README's figures from saved runs (./scripts/figures.sh makes them).

    figures.py save NAME RESULTS.json --command CMD    # an eval's summary -> docs/figures/NAME.json
    figures.py save-json NAME REPORT.json --command CMD  # a benchmark's JSON -> docs/figures/NAME.json
    figures.py render [--check]                        # README.md's table, and every page's figure spans

Each figure has one source, docs/figures/NAME.json, holding the command that made it;
tests/test_figures.py runs `render --check`, so a page's figure cannot drift from its run.
Elsewhere than the README's table a page quotes a figure as a span,

    <!--fig NAME PATH FORMAT-->15.34<!--/fig-->

NAME a file of docs/figures, PATH the dotted keys to the value in it (list items by
index, -1 the last), FORMAT its digits: `2` (15.34), `+2` (+1.80), `ci2` (15.34 [14.73,
16.08]) or `ci+2` (+1.80 [+1.49, +2.16]) for an interval, `neg` before any of them for the
other sign (B − A of a saved A − B). `render` writes the spans' text.
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path

from worldpack_train.card import fmt, interval, summarise

ROOT = Path(__file__).resolve().parent.parent
FIGURES = ROOT / "docs" / "figures"
README = ROOT / "README.md"
BEGIN = "<!-- figures: written by ./scripts/figures.sh render from docs/figures/*.json; edit those, not this table -->"
END = "<!-- /figures -->"
SPAN = re.compile(r"<!--fig ([\w-]+) ([\w.-]+) ([\w+]+)-->(.*?)<!--/fig-->")


def pages() -> list[Path]:
    """The user pages that may quote figures (the changelog and research notes keep theirs as dated)."""
    return [README, *sorted((ROOT / "docs").glob("*.md"))]


def load(name: str) -> dict:
    path = FIGURES / f"{name}.json"
    if not path.exists():
        raise SystemExit(f"{path.relative_to(ROOT)} is missing: run the command that makes it (./scripts/figures.sh)")
    return json.loads(path.read_text())


def db(i: dict) -> str:
    return f"{i['mean']:.2f} dB"


def gap(i: dict) -> str:
    """A paired difference with its interval."""
    return fmt(i, signed=True)


def share(i: dict) -> str:
    return f"{i['mean']:.2f}"


def code(command: str) -> str:
    return f"`{command}`"


def paper_row(world: str, name: str) -> list[str]:
    ev = load(f"{name}-paper")
    rows = ev["rows"]
    return [f"The paper's comparison, {world}: WorldPack against its 4-frame baseline, {ev['trajectories']} test walks",
            f"{db(rows['worldpack']['psnr'])} against {db(rows['baseline']['psnr'])}: "
            f"{gap(rows['baseline']['served_minus_row_db'])} dB", code(ev["command"])]


def served_row(what: str, name: str, baseline: bool = False) -> list[str]:
    ev = load(name)
    rows, new = ev["rows"], ev["strata"]["new_ground"]
    served, warp = rows["served_covisible"], rows["reproject_fused"]
    figure = (f"{db(served['psnr'])}; {gap(warp['served_minus_row_db'])} dB over the fused warp, at "
              f"{share(served['sharpness'])} of the truth's edge energy")
    if baseline:
        figure += f"; {gap(rows['baseline']['served_minus_row_db'])} dB over the 4-frame baseline"
    if new["frames"]:
        new_rows = new["rows"]
        figure += (f"; on new ground ({new['frames']:,} frames) {gap(new_rows['reproject_fused']['served_minus_row_db'])} dB, "
                   f"at {share(new_rows['served_covisible']['sharpness'])}")
    return [what.format(n=ev["trajectories"]), figure, code(ev["command"])]


def miniworld_row() -> list[str]:
    aba, abca = load("miniworld-aba"), load("miniworld-abca")
    both = lambda f: " and ".join(f(ev["rows"]) for ev in (aba, abca))
    figure = (f"{both(lambda r: db(r['served_covisible']['psnr']))}; over the fused warp "
              f"{both(lambda r: gap(r['reproject_fused']['served_minus_row_db']))} dB, at "
              f"{both(lambda r: share(r['served_covisible']['sharpness']))} of the truth's edge energy; over the "
              f"Doom model it started from {both(lambda r: gap(r['started_from_covisible']['served_minus_row_db']))} dB")
    return [f"MiniWorld's rooms (a world brought in through the trainer), {aba['trajectories']} ABA and "
            f"{abca['trajectories']} ABCA walks at world seeds never trained on", figure, code(aba["command"])]


def trainer_row(world: str) -> list[str] | None:
    """The model `worldpack train --from WORLD` made, beside the served one on the same walks."""
    if not (FIGURES / f"{world}-trainer.json").exists():
        return None
    ev = load(f"{world}-trainer")
    rows = ev["rows"]
    made, served = rows["command_covisible"], rows["served_covisible"]
    ahead = interval(made["served_minus_row_db"], flip=True)  # made − served
    return [f"The {'Doom' if world == 'doom' else world} model `worldpack train --from {world}` makes on 2 cores, "
            f"beside the served one, the same {ev['trajectories']} walks",
            f"{db(made['psnr'])} against {db(served['psnr'])}: {gap(ahead)} dB; {share(made['sharpness'])} of the "
            f"truth's edge energy against {share(served['sharpness'])}", code(ev["command"])]


def fullsize_row() -> list[str] | None:
    """The served models' frames at 224x224 (their sessions' own size) on the three worlds' held-out suites."""
    worlds = [("voxel", "fullsize-voxel"), ("Doom", "fullsize-doom"), ("MiniWorld", "fullsize-miniworld")]
    if not all((FIGURES / f"{n}.json").exists() and (FIGURES / f"{n}-fused.json").exists() for _, n in worlds):
        return None
    parts = []
    for world, name in worlds:
        served, fused = load(name)["rows"]["served_covisible"], load(f"{name}-fused")["rows"]["served_covisible"]
        parts.append(f"{world} {db(served['psnr'])}: {gap(interval(served['served_minus_row_db'], flip=True))} over the 64×64 "
                     f"frame brought up, {gap(interval(fused['served_minus_row_db'], flip=True))} over the fused warp, "
                     f"at {share(served['sharpness'])}")
    return ["Frames at 224×224, a session's own size: the served models on their held-out suites rendered at it",
            "; ".join(parts) + " of the truth's edge energy (dB)", code(load("fullsize-voxel")["command"])]


def speed_rows() -> list[list[str]]:
    walk, select = load("walk"), load("select-loop")
    w = walk["report"]["rows"][0]
    by_frames = {r["frames"]: r for r in select["report"]["rows"]}
    return [["A step of the main job on one core (the served voxel model)",
             f"{w['p50_ms'][-1]:.1f} ms median, {w['p99_ms'][-1]:.1f} ms p99 ({w['steps_per_s']:.0f} steps a second)",
             code(walk["command"])],
            ["Choosing memories, LoopNav-like walk",
             f"{by_frames[1600]['indexed_median_ms']:.2f} ms at 1,600 stored frames, "
             f"{by_frames[100000]['indexed_median_ms']:.1f} ms at 100,000", code(select["command"])]]


def table() -> str:
    rows = [paper_row("voxel world", "voxel-test"),
            served_row("The served voxel model, the same {n} walks", "voxel-test"),
            trainer_row("voxel"),
            served_row("The served Doom model, {n} walks on maps never trained on", "doom-test", baseline=True),
            trainer_row("doom"),
            miniworld_row(), fullsize_row(), *speed_rows()]
    lines = ["| what | figure | command |", "| --- | --- | --- |"]
    lines += [f"| {' | '.join(r)} |" for r in rows if r is not None]
    return "\n".join(lines)


def quoted(name: str, path: str, form: str) -> str:
    """A span's text: the value at `path` in docs/figures/NAME.json, written as `form` says."""
    value = load(name)
    try:
        for part in path.split("."):
            value = value[int(part)] if isinstance(value, list) else value[part]
    except (KeyError, IndexError, ValueError, TypeError):
        raise SystemExit(f"docs/figures/{name}.json has no `{path}`")
    m = re.fullmatch(r"(neg)?(ci)?(\+)?(\d)", form)
    if m is None:
        raise SystemExit(f"figure span {name} {path}: format {form!r} is not 2, +2, ci2 or ci+2 (neg before it flips the sign)")
    signed, digits = bool(m[3]), int(m[4])
    if m[2]:
        return fmt(interval(value, flip=bool(m[1])), signed=signed, digits=digits)
    return f"{-value if m[1] else value:{'+' if signed else ''}.{digits}f}"


def with_spans(text: str) -> str:
    return SPAN.sub(lambda m: f"<!--fig {m[1]} {m[2]} {m[3]}-->{quoted(m[1], m[2], m[3])}<!--/fig-->", text)


def with_table(text: str, name: str) -> str:
    if BEGIN not in text or END not in text:
        raise SystemExit(f"{name}: the figures' markers are missing ({BEGIN!r} ... {END!r})")
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{table()}\n{END}{tail}"


def render(readme: Path, check: bool) -> int:
    """The README's table and every page's spans from the saved runs; with `check`, only
    says which pages differ."""
    stale = []
    for page in dict.fromkeys([readme, *pages()]):
        text = page.read_text()
        new = with_spans(with_table(text, page.name) if page == readme else text)
        if new != text:
            stale.append(page)
            if not check:
                page.write_text(new)
    if check and stale:
        names = ", ".join(str(p.relative_to(ROOT)) if p.is_relative_to(ROOT) else str(p) for p in stale)
        print(f"figures on {names} differ from docs/figures/*.json: run ./scripts/figures.sh render", file=sys.stderr)
        return 1
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    for name, helptext in (("save", "an eval's results.json"), ("save-json", "a benchmark's --json output")):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("name")
        s.add_argument("source", type=Path)
        s.add_argument("--command", required=True, help="the command that reproduces it, as a user runs it")
    r = sub.add_parser("render", help="README.md's table and the pages' figure spans from docs/figures/*.json")
    r.add_argument("--check", action="store_true", help="fail, changing nothing, when a page differs")
    r.add_argument("--readme", type=Path, default=README, help="the page to render into (default: README.md)")
    a = ap.parse_args()
    if a.what == "render":
        return render(a.readme, a.check)
    report = json.loads(a.source.read_text())
    body = summarise(report) if a.what == "save" else {"report": report}
    FIGURES.mkdir(parents=True, exist_ok=True)
    (FIGURES / f"{a.name}.json").write_text(json.dumps({"command": a.command, **body}, indent=1) + "\n")
    print(f"wrote docs/figures/{a.name}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())
