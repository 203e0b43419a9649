"""Draws the synthetic world's pictures for docs/world.md.

    cargo build --release && .venv/bin/python scripts/world_pictures.py

Writes docs/world/biomes.png (RGB and depth from six biomes), and
docs/world/paths.png (top-down maps of an ABA and an ABCA trajectory).
"""

import json
import os
import subprocess
import sys
import tempfile

import cv2
import numpy as np

ROOT = os.path.join(os.path.dirname(__file__), "..")
BIN = os.environ.get("WORLDPACK_BIN", os.path.join(ROOT, "target", "release", "worldpack"))
OUT = os.path.join(ROOT, "docs", "world")
BIOMES = ["plains", "forest", "desert", "snowy", "mountains", "badlands"]


def worldpack(*args):
    subprocess.run([BIN, *args], check=True, stdout=subprocess.DEVNULL)


def label(img, text):
    img = img.copy()
    cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (255, 255, 255), 1, cv2.LINE_AA)
    return img


def pad_to(img, h):
    return np.pad(img, ((0, h - img.shape[0]), (0, 6), (0, 0)), constant_values=255)


def main():
    os.makedirs(OUT, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        rgb, depth = [], []
        for b in BIOMES:
            d = os.path.join(tmp, b)
            worldpack("sim", "render", "--seed", "3", "--biome", b, "--size", "160x160", "--out", d)
            rgb.append(label(cv2.imread(os.path.join(d, "rgb.png")), b))
            depth.append(cv2.imread(os.path.join(d, "depth.png")))
        cv2.imwrite(os.path.join(OUT, "biomes.png"), np.concatenate([np.concatenate(rgb, 1), np.concatenate(depth, 1)], 0))

        suite = os.path.join(tmp, "suite")
        worldpack("sim", "loopnav", "--per-cell", "1", "--ranges", "30", "--out", suite)
        index = json.load(open(os.path.join(suite, "index.json")))
        maps = []
        for t in index["trajectories"]:
            img = cv2.imread(os.path.join(suite, t["dir"], "topdown.png"))
            maps.append(label(img, f"{t['task'].upper()}-{t['range']}: {t['frames']} frames"))
        h = max(m.shape[0] for m in maps)
        cv2.imwrite(os.path.join(OUT, "paths.png"), np.concatenate([pad_to(m, h) for m in maps], 1))

        # A film strip along the ABCA trajectory: every 8th of its frames.
        abca = [t for t in index["trajectories"] if t["task"] == "abca"][0]
        frames = np.load(os.path.join(suite, abca["dir"], "rgb.npy"))
        picks = np.linspace(0, len(frames) - 1, 10).astype(int)
        strip = np.concatenate([cv2.resize(frames[i], (128, 128), interpolation=cv2.INTER_NEAREST) for i in picks], 1)
        cv2.imwrite(os.path.join(OUT, "abca_strip.png"), cv2.cvtColor(strip, cv2.COLOR_RGB2BGR))
    print("wrote", ", ".join(sorted(os.listdir(OUT))), "in", OUT, file=sys.stderr)


if __name__ == "__main__":
    main()
