"""Walk one trajectory of any suite in the dataset format through a served model, over
REST: create a session from its first frame and intrinsics, observe the way out (frames,
depth, poses, actions) as a camera would record it, generate the way back at the
recorded poses, and score every generated frame against the recorded one.

    ./scripts/serve.sh --model fixtures/miniworld/geometry_fused &      # served as its manifest says
    python clients/python/examples/suite_walk.py --suite data/mw-test-aba --index 0 --out walk.png

Your own frames work the same way once written in the format (docs/dataset.md). Needs
the client (`pip install -e clients/python`) and the project's metrics
(`pip install --no-deps -e train`: numpy only).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

from worldpack_client import Client
from worldpack_train.metrics import psnr, sharpness_ratio

KEYS = ("forward", "back", "left", "right", "jump")


def action(row: np.ndarray) -> dict:
    """A row of actions.npy (forward, back, left, right, jump, yaw Δ, pitch Δ) as the API's action."""
    out = {k: bool(v) for k, v in zip(KEYS, row[:5]) if v}
    out.update({"yaw_deg": float(row[5]), "pitch_deg": float(row[6])})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--suite", type=Path, required=True, help="a suite folder (index.json and one folder per walk)")
    ap.add_argument("--index", type=int, default=0, help="which walk of the suite")
    ap.add_argument("--every", type=int, default=4, help="one column of the picture every this many generated frames")
    ap.add_argument("--out", default="suite_walk.png")
    a = ap.parse_args()

    entries = json.loads((a.suite / "index.json").read_text())["trajectories"]
    if not 0 <= a.index < len(entries):
        raise SystemExit(f"--index: {a.suite} has walks 0..{len(entries) - 1}, not {a.index}")
    entry = entries[a.index]
    walk = a.suite / entry["dir"]
    meta = json.loads((walk / "meta.json").read_text())
    rgb, poses, actions = (np.load(walk / f"{n}.npy") for n in ("rgb", "poses", "actions"))
    depth = np.load(walk / "depth.npy") if (walk / "depth.npy").exists() else None
    back = entry["returning_point"]

    client = Client(a.url)
    session = client.create_session(frames=[(rgb[0], poses[0])], intrinsics=meta["intrinsics"])
    for t in range(1, back):  # the way out, observed with depth
        client.observe(session, rgb[t], poses[t], depth_mm=None if depth is None else depth[t], action=action(actions[t]))
    print(f"{walk.name}: observed {back} frames of the way out; generating the {len(rgb) - back} of the way back")
    generated, columns = [], []
    for i, t in enumerate(range(back, len(rgb))):
        step = client.step(session, action(actions[t]), pose=poses[t])
        generated.append(step.image)
        if i % a.every == 0:
            columns.append(np.concatenate([rgb[t], np.full((2, rgb.shape[2], 3), 255, np.uint8), step.image], axis=0))
    client.delete_session(session)

    made, truth = np.stack(generated), rgb[back:]
    per_frame = [psnr(m, t) for m, t in zip(made, truth)]
    print(f"way back: {len(made)} frames, PSNR {np.mean(per_frame):.2f} dB (the mean over frames, as eval pools it: a frame "
          f"identical to the recorded one counts 100 dB), "
          f"sharpness {sharpness_ratio(made, truth):.2f} of the truth's; the last observed frame held still: "
          f"{np.mean([psnr(rgb[back - 1], t) for t in truth]):.2f} dB")
    gap = np.full((columns[0].shape[0], 2, 3), 255, np.uint8)
    strip = np.concatenate([c for col in columns for c in (col, gap)][:-1], axis=1)
    Image.fromarray(strip).resize((strip.shape[1] * 3, strip.shape[0] * 3), Image.NEAREST).save(a.out)
    print(f"wrote {a.out}: the recorded frame (top) over the generated one (bottom)")


if __name__ == "__main__":
    main()
