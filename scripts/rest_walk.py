"""An out-and-back walk through the REST API, scored against the synthetic world.

For each row (a model folder and a policy) this starts `worldpack serve` on a
free local port with its own store, opens a synthetic session, looks around
(12 turns of 30 degrees), walks 20 steps out, turns back (6 turns of 30
degrees) and walks 20 steps back along the same path. Every step answer
carries the PSNR/SSIM of the generated frame against the world's true frame
at its pose; the script keeps them, fetches frames for a picture, and writes:

  <out>.json   per-step PSNR/SSIM per row, with the phase of each step
  <out>.png    the PSNR curves, phases marked
  <out>-strip.png  every 4th frame of the way back: truth, then each row

With --observe-outbound the look-around and the way out are observing steps
(`"observe": true`: the world's true frame and depth are recorded, as a
robot's camera would), and only the turn and the way back are generated: the
LoopNav protocol through the API, where a geometry model can warp what was seen.

    .venv/bin/python scripts/rest_walk.py --out docs/results/rest_walk \\
        --row worldpack=fixtures/variants/worldpack:worldpack --row baseline=fixtures/variants/baseline:baseline

One walk is one world and a few dozen frames. `--worlds 1-24` walks the same
path in each of those synthetic worlds (pictures for the first) and adds the
way back per world and, for every row after the first, its mean difference
from the first row with a 95% bootstrap interval over worlds, the median
difference and the world where the row is furthest behind. One walk is also
one draw of the sampler's noise: `--draws 16` walks each world 16 times with
other step seeds, and with a single world the interval is over those draws
(is a difference the model's, or the noise's?). A row may name its own sampler
steps (`NAME=FOLDER:POLICY:STEPS`), so a 10-step model and a 5-step one can be
walked side by side. `--reuse OLD.json:NAME` takes a row from an earlier walk
of the same worlds and draws instead of walking it again (the same step seeds
give the same frames), so a candidate is paired against a slow model's cached
walk; reused rows come first, in the order given.

Standard library, NumPy and OpenCV only (the test venv)."""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

import cv2
import numpy as np

LOOK, OUT, TURN, BACK = 12, 20, 6, 20


def walk() -> list[tuple[str, dict]]:
    """The actions, each with its phase."""
    steps = [("look around", {"yaw_deg": 30.0})] * LOOK
    steps += [("out", {"forward": True})] * OUT
    steps += [("turn back", {"yaw_deg": 30.0})] * TURN
    steps += [("back", {"forward": True})] * BACK
    return steps


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def call(url: str, body: dict | None = None) -> dict | bytes:
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, headers={"content-type": "application/json"} if data else {})
    try:
        with urllib.request.urlopen(req, timeout=120) as r:
            raw = r.read()
            return json.loads(raw) if r.headers.get("content-type", "").startswith("application/json") else raw
    except urllib.error.HTTPError as e:
        sys.exit(f"{url}: HTTP {e.code}: {e.read().decode(errors='replace')}")


def png_to_rgb(png: bytes) -> np.ndarray:
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


OBSERVABLE = ("look around", "out")
SEEDS_PER_DRAW = 1000  # a draw's step seeds: draw 0 takes 1, 2, ...; draw k takes 1000 k + 1, ...


def run_row(binary: str, model: str, policy: str, seed: int, steps: int, method: str, observe_outbound: bool = False,
            covisible: bool = False, draw: int = 0) -> dict:
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        server = subprocess.Popen([binary, "serve", "--model", model, "--store", f"{tmp}/walk.redb", "--addr", f"127.0.0.1:{port}",
                                   "--policy", policy, "--steps", str(steps), "--method", method] + (["--covisible"] if covisible else []),
                                  stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        base = f"http://127.0.0.1:{port}"
        try:
            for _ in range(600):
                try:
                    call(f"{base}/v1/health")
                    break
                except (urllib.error.URLError, ConnectionError):
                    if server.poll() is not None:
                        sys.exit(f"worldpack serve --model {model} stopped: {server.stderr.read().decode()}")
                    time.sleep(0.1)
            session = call(f"{base}/v1/sessions", {"synthetic": {"seed": seed}})["session"]
            rows = []
            for phase, action in walk():
                observe = observe_outbound and phase in OBSERVABLE
                r = call(f"{base}/v1/sessions/{session}/step", {"action": action, "seed": SEEDS_PER_DRAW * draw + len(rows) + 1,
                                                                      "observe": observe})
                truth = r["truth"] or {"psnr_db": None, "ssim": None}  # an observed frame is the truth
                rows.append({"index": r["index"], "phase": phase, "psnr_db": truth["psnr_db"], "ssim": truth["ssim"],
                             "warp_frames": r["selection"]["warp_frames"]})
            back = [r["index"] for r in rows if r["phase"] == "back"][::4]
            frames = {i: png_to_rgb(call(f"{base}/v1/sessions/{session}/frames/{i}/image")) for i in back}
            truths = {i: png_to_rgb(call(f"{base}/v1/sessions/{session}/frames/{i}/truth")) for i in back}
            return {"model": model, "policy": policy, "steps": rows, "frames": frames, "truths": truths}
        finally:
            server.terminate()
            server.wait(timeout=30)


def curve(results: dict, path: Path) -> None:
    w, h, pad = 720, 320, 40
    img = np.full((h, w, 3), 255, np.uint8)
    n = len(next(iter(results.values()))["steps"])
    values = [s["psnr_db"] for r in results.values() for s in r["steps"] if s["psnr_db"] is not None]
    lo, hi = np.floor(min(values)) - 1, np.ceil(max(values)) + 1
    x = lambda i: int(pad + (w - 2 * pad) * i / max(n - 1, 1))
    y = lambda v: int(h - 2 * pad - (h - 3 * pad) * (v - lo) / (hi - lo))
    start = 0
    for phase, length in [("look around", LOOK), ("out", OUT), ("turn back", TURN), ("back", BACK)]:
        cv2.line(img, (x(start), pad), (x(start), h - 2 * pad), (200, 200, 200), 1)
        cv2.putText(img, phase, (x(start) + 3, pad - 8), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (90, 90, 90), 1, cv2.LINE_AA)
        start += length
    for v in np.arange(lo, hi + 0.1, 2):
        cv2.putText(img, f"{v:.0f}", (4, y(v) + 4), cv2.FONT_HERSHEY_SIMPLEX, 0.35, (90, 90, 90), 1, cv2.LINE_AA)
    colours = [(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40)]
    for k, (name, r) in enumerate(results.items()):
        c = colours[k % len(colours)][::-1]
        pts = np.array([(x(i), y(s["psnr_db"])) for i, s in enumerate(r["steps"]) if s["psnr_db"] is not None], np.int32)
        if len(pts):
            cv2.polylines(img, [pts], False, c, 2, cv2.LINE_AA)
        # Legend along the bottom, below the curves.
        cv2.line(img, (pad + 170 * k, h - 28), (pad + 170 * k + 20, h - 28), c, 3)
        cv2.putText(img, name, (pad + 170 * k + 25, h - 24), cv2.FONT_HERSHEY_SIMPLEX, 0.4, c, 1, cv2.LINE_AA)
    cv2.putText(img, "PSNR (dB) against the true frame, per REST step", (pad, h - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.imwrite(str(path), img)


def strip(results: dict, path: Path, scale: int = 2) -> None:
    first = next(iter(results.values()))
    indices = sorted(first["truths"])
    rows = [("truth", [first["truths"][i] for i in indices])] + [(n, [r["frames"][i] for i in indices]) for n, r in results.items()]
    # As wide as the longest name needs: labels are never cut.
    font, size = cv2.FONT_HERSHEY_SIMPLEX, 0.38
    label_w = 12 + max(cv2.getTextSize(name, font, size, 1)[0][0] for name, _ in rows)
    tiles = []
    for name, images in rows:
        line = np.concatenate([cv2.resize(im, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST) for im in images], axis=1)
        label = np.full((line.shape[0], label_w, 3), 255, np.uint8)
        cv2.putText(label, name, (4, line.shape[0] // 2), font, size, (0, 0, 0), 1, cv2.LINE_AA)
        tiles.append(np.concatenate([label, line], axis=1))
    cv2.imwrite(str(path), cv2.cvtColor(np.concatenate(tiles, axis=0), cv2.COLOR_RGB2BGR))


def worlds_of(spec: str) -> list[int]:
    """`3`, `1-24` or `1,5,9`: the synthetic worlds' seeds."""
    try:
        if "-" in spec:
            lo, hi = (int(x) for x in spec.split("-"))
            seeds = list(range(lo, hi + 1))
        else:
            seeds = [int(x) for x in spec.split(",")]
    except ValueError:
        seeds = []
    if not seeds or min(seeds) < 0:
        sys.exit(f"--worlds {spec!r}: expected a seed, a range A-B or a list A,B,C of seeds >= 0")
    return seeds


def row_of(spec: str, default_steps: int) -> tuple[str, str, str, int]:
    """`NAME=FOLDER:POLICY` or `NAME=FOLDER:POLICY:STEPS` -> (name, folder, policy, steps)."""
    name, _, rest = spec.partition("=")
    model, _, policy = rest.rpartition(":")
    steps = default_steps
    if policy.isdigit():
        steps = int(policy)
        model, _, policy = model.rpartition(":")
    if not (name and model and policy) or steps < 1:
        sys.exit(f"--row {spec!r}: expected NAME=MODEL_FOLDER:POLICY or NAME=MODEL_FOLDER:POLICY:STEPS (STEPS >= 1)")
    return name, model, policy, steps


def reused_row(spec: str, worlds: list[int], draws: int, observe_outbound: bool, covisible: bool) -> tuple[dict, list, int]:
    """`OLD.json:NAME` -> (that row's first walk, its way back per world and draw, its sampler steps),
    refused unless the earlier walk covered the same worlds and draws the same way."""
    path, _, name = spec.rpartition(":")
    try:
        old = json.loads(Path(path).read_text())
        walks = old["rows"]
        if name not in walks:
            sys.exit(f"--reuse {spec!r}: {path} has no row {name!r}; it has {', '.join(walks) or 'none'}")
        across = old.get("across_worlds") or {"worlds": [old["seed"]], "draws": 1,
                                              "way_back_db": {name: [[round(way_back(walks[name]["steps"]), 2)]]}}
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as e:
        sys.exit(f"--reuse {spec!r}: cannot read {path!r} as this script's JSON ({type(e).__name__}: {e})")
    same = {"worlds": (across["worlds"], worlds), "draws": (across["draws"], draws),
            "--observe-outbound": (old.get("observe_outbound"), observe_outbound),
            "--covisible": (old.get("covisible", covisible), covisible)}
    for what, (theirs, ours) in same.items():
        if theirs != ours:
            sys.exit(f"--reuse {spec!r}: that walk had {what} {theirs}, this one {ours}")
    return walks[name], across["way_back_db"][name], old.get("steps_per_row", {}).get(name)


def way_back(steps: list[dict]) -> float:
    return float(np.mean([s["psnr_db"] for s in steps if s["phase"] == "back"]))


def paired(first: list[float], other: list[float], ids: list[int], resamples: int = 2000) -> dict:
    """Mean of other - first over units (worlds, or one world's draws, named by `ids`), a 95%
    bootstrap interval, the wins, the median, and the unit where other is furthest behind (a
    mean can hide a few large losses)."""
    d = np.asarray(other) - np.asarray(first)
    rng = np.random.default_rng(0)
    means = d[rng.integers(0, len(d), (resamples, len(d)))].mean(axis=1)
    worst = int(np.argmin(d))
    return {"diff_db": round(float(d.mean()), 2), "ci95": [round(float(np.percentile(means, q)), 2) for q in (2.5, 97.5)],
            "wins": int((d > 0).sum()), "units": len(d), "median_db": round(float(np.median(d)), 2),
            "worst": {"unit": ids[worst], "diff_db": round(float(d[worst]), 2)}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--row", action="append", default=[], help="NAME=MODEL_FOLDER:POLICY[:STEPS] (repeatable; STEPS overrides --steps for this row)")
    ap.add_argument("--reuse", action="append", default=[], metavar="OLD.json:NAME",
                    help="a row from an earlier walk of the same worlds and draws, not walked again (repeatable; before the --row rows)")
    ap.add_argument("--bin", default="target/release/worldpack")
    ap.add_argument("--seed", type=int, default=3, help="the synthetic world (see --worlds for many)")
    ap.add_argument("--worlds", help="walk in each of these worlds: a range A-B or a list A,B,C (overrides --seed)")
    ap.add_argument("--draws", type=int, default=1,
                    help="walk each world this many times, each with other seeds for the sampler's noise (draw 0 is "
                         "the single walk's); a world's way back is the mean over its draws")
    ap.add_argument("--steps", type=int, default=10, help="sampler steps per frame")
    ap.add_argument("--method", default="ddim")
    ap.add_argument("--covisible", action="store_true", help="serve with --covisible, as ./scripts/serve.sh does")
    ap.add_argument("--out", type=Path, required=True, help="path prefix for .json, .png and -strip.png")
    ap.add_argument("--observe-outbound", action="store_true",
                    help="observe the look-around and the way out (the world's frames and depth); generate only the way back")
    a = ap.parse_args()
    worlds = worlds_of(a.worlds) if a.worlds else [a.seed]
    if a.draws < 1:
        sys.exit(f"--draws {a.draws}: expected at least 1")
    if not a.row and not a.reuse:
        sys.exit("--row: give at least one row to walk (or --reuse one)")
    rows = [row_of(spec, a.steps) for spec in a.row]
    reused = [(spec.rpartition(":")[2], spec) for spec in a.reuse]
    names = [name for name, _ in reused] + [name for name, *_ in rows]
    if len(set(names)) < len(names):
        sys.exit(f"--row/--reuse: each row needs its own name, got {', '.join(names)}")
    results, per_world, steps_per_row = {}, {}, {}
    for name, spec in reused:
        results[name], per_world[name], steps_per_row[name] = reused_row(spec, worlds, a.draws, a.observe_outbound, a.covisible)
    for name, model, policy, steps in rows:
        steps_per_row[name] = steps
        print(f"{name}: {model} with {policy}, {steps} sampler steps", flush=True)
        for k, seed in enumerate(worlds):
            backs = []
            for draw in range(a.draws):
                r = run_row(a.bin, model, policy, seed, steps, a.method, a.observe_outbound, a.covisible, draw)
                backs.append(way_back(r["steps"]))
                if k == 0 and draw == 0:
                    results[name] = r
            per_world.setdefault(name, []).append(backs)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    summary = {}
    for name, r in results.items():
        by_phase = {}
        for s in r["steps"]:
            if s["psnr_db"] is not None:
                by_phase.setdefault(s["phase"], []).append(s["psnr_db"])
        summary[name] = {p: round(float(np.mean(v)), 2) for p, v in by_phase.items()}
        print(f"{name:>12}: " + ", ".join(f"{p} {v:.2f} dB" for p, v in summary[name].items()))
    first = next(iter(results))
    across = None
    if len(worlds) > 1 or a.draws > 1:
        # The unit of the interval: a world (the mean of its draws), or with one world, a draw of its noise.
        unit = "worlds" if len(worlds) > 1 else "draws"
        units = {n: [float(np.mean(b)) for b in bs] if unit == "worlds" else bs[0] for n, bs in per_world.items()}
        ids = worlds if unit == "worlds" else list(range(a.draws))
        across = {"worlds": worlds, "draws": a.draws, "unit": unit,
                  "way_back_db": {n: [[round(v, 2) for v in b] for b in bs] for n, bs in per_world.items()},
                  "mean_way_back_db": {n: round(float(np.mean(vs)), 2) for n, vs in units.items()},
                  f"against_{first}": {n: paired(units[first], vs, ids) for n, vs in units.items() if n != first}}
        print(f"the way back over {len(worlds)} world(s) ({worlds[0]}..{worlds[-1]}), {a.draws} draw(s) each, per {unit[:-1]}:")
        for n, vs in units.items():
            line = f"{n:>12}: {np.mean(vs):.2f} dB"
            if n != first:
                p = across[f"against_{first}"][n]
                line += (f", {p['diff_db']:+.2f} [{p['ci95'][0]:+.2f}, {p['ci95'][1]:+.2f}] against {first}, ahead in {p['wins']} of {p['units']} {unit}"
                         f"; median {p['median_db']:+.2f}, furthest behind {p['worst']['diff_db']:+.2f} ({unit[:-1]} {p['worst']['unit']})")
            print(line)
    record = {"command": " ".join(sys.argv), "seed": worlds[0], "sampler": f"{a.method}, {a.steps} steps",
              "steps_per_row": steps_per_row, "observe_outbound": a.observe_outbound, "covisible": a.covisible,
              "mean_psnr_db_by_phase": summary,
              "rows": {n: {k: v for k, v in r.items() if k not in ("frames", "truths")} for n, r in results.items()}}
    if across:
        record["across_worlds"] = across
    a.out.with_suffix(".json").write_text(json.dumps(record, indent=1))
    curve(results, a.out.with_suffix(".png"))
    walked = {n: r for n, r in results.items() if "frames" in r}  # a reused row kept no frames
    if walked:
        strip(walked, Path(f"{a.out}-strip.png"))
    print(f"wrote {a.out}.json, {a.out}.png" + (f", {a.out}-strip.png" if walked else ""))


if __name__ == "__main__":
    main()
