"""python -m worldpack_miniworld suite --split train|test [--task aba|abca|mixed] --count N [--seed S] --out DIR"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from . import engine as E
from .engine import GL_MODES, GLUnavailable
from .suite import (DEFAULT_RANGES, HELD_OUT_ENVS, MAX_SEED, SEED_BASE, SEED_BLOCK, SPLIT_ENVS, TASK_CHOICES,
                    TRAIN_ENVS, write_suite)

MAX_COUNT = 10_000
MAX_RANGE = 20.0       # metres; the largest environment (Maze) is 26 m across


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="worldpack_miniworld", description="MiniWorld walks as a WorldPack suite")
    sub = p.add_subparsers(dest="command", required=True)
    s = sub.add_parser("suite", help="write out-and-back walks in the worldpack-suite/1 format")
    s.add_argument("--split", choices=["train", "test"], required=True,
                   help=f"train: {','.join(TRAIN_ENVS)} at world seeds {SEED_BASE['train']}..; test (held out): the same "
                        f"at world seeds {SEED_BASE['test']}.., and {','.join(HELD_OUT_ENVS)}")
    s.add_argument("--envs", help="comma-separated environment ids instead of the split's own (must stay within the split)")
    s.add_argument("--task", choices=TASK_CHOICES, default="aba",
                   help="aba: out to B and back the same way; abca: out to B, on to C, back to A another way; "
                        "mixed: the two in turn")
    s.add_argument("--count", type=int, required=True, help="walks in all, spread evenly over the environments")
    s.add_argument("--ranges", default=",".join(f"{r:g}" for r in DEFAULT_RANGES),
                   help="comma-separated ranges in metres (B is 0.8 to 1.2 ranges from A)")
    s.add_argument("--seed", type=int, default=0,
                   help=f"0..{MAX_SEED}: the suite's block of {SEED_BLOCK} world seeds in its split (suites with "
                        "different seeds share no world)")
    s.add_argument("--gl", choices=GL_MODES, default="egl",
                   help="egl: headless through Mesa's EGL (default); x11: the X display in DISPLAY (e.g. xvfb-run -a)")
    s.add_argument("--size", type=int, default=E.SIZE,
                   help=f"frame side in pixels (square): {E.SIZE} for the models, 224 for full-size eval")
    s.add_argument("--out", type=Path, required=True, help="a new or empty folder")
    return p


def main(argv: list[str] | None = None) -> None:
    p = parser()
    a = p.parse_args(argv)
    allowed = SPLIT_ENVS[a.split]
    envs = [e.strip() for e in a.envs.split(",")] if a.envs is not None else list(allowed)
    outside = [e for e in envs if e not in allowed]
    if not envs or outside:
        p.error(f"--envs: {','.join(outside) or 'none given'} not in the {a.split} environments ({','.join(allowed)})")
    if len(set(envs)) != len(envs):
        p.error("--envs: an environment is named twice")
    if not 1 <= a.count <= MAX_COUNT:
        p.error(f"--count: must be 1 to {MAX_COUNT} (got {a.count})")
    try:
        ranges = [float(r) for r in a.ranges.split(",")]
    except ValueError:
        p.error(f"--ranges: {a.ranges!r} is not a comma-separated list of numbers")
    if not all(0 < r <= MAX_RANGE for r in ranges):
        p.error(f"--ranges: every range must be above 0 and at most {MAX_RANGE:g} m (got {a.ranges})")
    if not 0 <= a.seed <= MAX_SEED:
        p.error(f"--seed: must be 0 to {MAX_SEED} (got {a.seed})")
    if not 8 <= a.size <= 1024:
        p.error(f"--size: must be 8 to 1024 pixels (got {a.size})")
    if a.out.exists() and (not a.out.is_dir() or any(a.out.iterdir())):
        p.error(f"--out: {a.out} exists and is not an empty folder")
    try:
        write_suite(a.out, a.split, envs, a.count, ranges, a.seed, task=a.task, gl=a.gl, size=a.size)
    except GLUnavailable as e:
        print(f"worldpack_miniworld: {e}", file=sys.stderr)
        sys.exit(1)


if __name__ == "__main__":
    main()
