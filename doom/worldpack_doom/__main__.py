"""python -m worldpack_doom suite --split train|test [--task aba|abca] --count N --out DIR"""

from __future__ import annotations

import argparse
from pathlib import Path

from .suite import TEST_MAPS, TRAIN_MAPS, write_suite
from .walk import TASKS


def main() -> None:
    p = argparse.ArgumentParser(prog="worldpack_doom", description="Doom (ViZDoom, freedoom2) walks as a WorldPack suite")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("suite", help="write out-and-back walks in the worldpack-suite/1 format")
    s.add_argument("--split", choices=["train", "test"], required=True,
                   help=f"train: {','.join(TRAIN_MAPS)}; test (held out): {','.join(TEST_MAPS)}")
    s.add_argument("--maps", help="comma-separated maps instead of the split's own (must stay within the split)")
    s.add_argument("--task", choices=sorted(TASKS), default="aba",
                   help="aba: out to B and back the same way; abca: out to B, on to C, back to A another way")
    s.add_argument("--count", type=int, required=True, help="walks in all, spread over the maps")
    s.add_argument("--ranges", default="4,8,12", help="comma-separated ranges in metres (B is at least 0.8 range from A)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--workers", type=int, default=1, help="maps rendered at once (processes)")
    s.add_argument("--size", type=int, default=64,
                   help="frame side in pixels (square; from the 320x240 screen's centre 200 columns): 64 for the models, 224 for full-size eval")
    s.add_argument("--out", type=Path, required=True)
    a = p.parse_args()
    allowed = TRAIN_MAPS if a.split == "train" else TEST_MAPS
    maps = a.maps.split(",") if a.maps else allowed
    outside = [m for m in maps if m not in allowed]
    if outside:
        p.error(f"--maps: {','.join(outside)} not in the {a.split} maps ({','.join(allowed)})")
    if a.count < 1:
        p.error("--count: must be at least 1")
    ranges = [float(r) for r in a.ranges.split(",")]
    if any(r <= 0 for r in ranges):
        p.error("--ranges: every range must be above 0")
    if not 8 <= a.size <= 1024:
        p.error(f"--size: between 8 and 1024 pixels, got {a.size}")
    write_suite(a.out, a.split, maps, a.count, ranges, a.seed, workers=a.workers, task=a.task, size=a.size)


if __name__ == "__main__":
    main()
