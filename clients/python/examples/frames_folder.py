"""A folder of plain frames, as a camera rig or a renderer leaves them, from one walk of a
suite in the dataset format: numbered PNG images, 16-bit depth PNGs and `cameras.json`
with the intrinsics and each frame's camera-to-world pose in OpenGL's axes (as Blender and
NeRF datasets write them). `own_frames.py` reads such a folder; this makes one to try it
on when you have none of your own.

    target/release/worldpack sim loopnav --per-cell 1 --ranges 15 --seed 5 --size 128x128 --out data/demo
    python clients/python/examples/frames_folder.py data/demo --out my-frames
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

# OpenCV's camera axes (x right, y down, z forward) to OpenGL's (x right, y up, z back).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("suite", type=Path, help="a suite folder in the dataset format")
    ap.add_argument("--index", type=int, default=0, help="which walk of the suite")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    entries = json.loads((a.suite / "index.json").read_text())["trajectories"]
    if not 0 <= a.index < len(entries):
        raise SystemExit(f"--index: {a.suite} has walks 0..{len(entries) - 1}, not {a.index}")
    walk = a.suite / entries[a.index]["dir"]
    meta = json.loads((walk / "meta.json").read_text())
    rgb, poses = np.load(walk / "rgb.npy"), np.load(walk / "poses.npy")
    depth = np.load(walk / "depth.npy") if (walk / "depth.npy").exists() else None
    a.out.mkdir(parents=True, exist_ok=True)
    frames = []
    for t in range(len(rgb)):
        Image.fromarray(rgb[t]).save(a.out / f"{t:04d}.png")
        frame = {"image": f"{t:04d}.png", "pose": (poses[t] @ CV_TO_GL).tolist()}
        if depth is not None:
            Image.fromarray(depth[t]).save(a.out / f"{t:04d}-depth.png")
            frame["depth"] = f"{t:04d}-depth.png"
        frames.append(frame)
    cameras = {"intrinsics": meta["intrinsics"], "convention": "opengl", "frames": frames}
    (a.out / "cameras.json").write_text(json.dumps(cameras, indent=1))
    print(f"wrote {len(frames)} frames of {walk.name} ({rgb.shape[2]}x{rgb.shape[1]}) and cameras.json to {a.out}; "
          f"the walk turns back after frame {entries[a.index]['returning_point'] - 1}")


if __name__ == "__main__":
    main()
