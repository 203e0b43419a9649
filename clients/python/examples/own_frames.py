"""Your own frames through a served model, over REST: a folder of images with camera poses
and intrinsics (and depth, if you have it) becomes a session; the first frames are
observed as a camera recorded them, and the model generates the frames at the remaining
poses, which are scored against your held-back images.

    ./scripts/serve.sh &                                        # the served voxel model
    python clients/python/examples/own_frames.py my-frames/ --observe 40 --out made/

The folder (docs/quickstart.md): images (PNG or JPEG, any one size up to the server's
--max-frame-side; the model sees them at its 64x64, the session answers at theirs) and `cameras.json`:

    {"intrinsics": {"fx": 89.6, "fy": 89.6, "cx": 63.5, "cy": 63.5, "width": 128, "height": 128,
                    "near": 0.1, "far": 64.0},
     "convention": "opengl",           # opencv: camera-to-world, x right, y down, z forward (default)
                                       # opengl: camera-to-world, x right, y up, z back (Blender, NeRF)
     "frames": [{"image": "000.png", "pose": [[...4 rows...]], "depth": "000-depth.png"}, ...]}

`depth` is optional: a 16-bit PNG of planar depth in millimetres of the poses' unit
(0 = unknown); without it the geometry model has no warp. Needs the client
(`pip install -e clients/python`) and the project's metrics (`pip install --no-deps -e train`).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from PIL import Image

from worldpack_client import Client, opengl
from worldpack_train.metrics import psnr, sharpness_ratio

CONVENTIONS = ("opencv", "opengl")


def read_folder(folder: Path) -> tuple[dict, list[dict]]:
    """cameras.json, checked, and its frames with their images loaded."""
    path = folder / "cameras.json"
    if not path.exists():
        raise SystemExit(f"{folder}: no cameras.json (intrinsics, convention, frames: see this file's docstring)")
    cams = json.loads(path.read_text())
    convention = cams.get("convention", "opencv")
    if convention not in CONVENTIONS:
        raise SystemExit(f"{path}: field `convention`: one of {', '.join(CONVENTIONS)}, got {convention!r}")
    if "intrinsics" not in cams or not cams.get("frames"):
        raise SystemExit(f"{path}: fields `intrinsics` and `frames` (a non-empty list) are required")
    frames = []
    for i, f in enumerate(cams["frames"]):
        pose = np.asarray(f.get("pose"), float)
        if pose.shape != (4, 4):
            raise SystemExit(f"{path}: field `frames[{i}].pose`: a 4x4 camera-to-world matrix, got shape {pose.shape}")
        image = np.asarray(Image.open(folder / f["image"]).convert("RGB"))
        depth = np.asarray(Image.open(folder / f["depth"])).astype(np.uint16) if f.get("depth") else None
        frames.append({"image": image, "pose": opengl(pose) if convention == "opengl" else pose, "depth": depth})
    return cams, frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder", type=Path, help="images and cameras.json")
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--observe", type=int, help="frames observed before the model takes over (default: three quarters)")
    ap.add_argument("--out", type=Path, default=Path("made"), help="generated frames and strip.png are written here")
    a = ap.parse_args()

    cams, frames = read_folder(a.folder)
    observe = a.observe if a.observe is not None else (3 * len(frames)) // 4
    if not 1 <= observe < len(frames):
        raise SystemExit(f"--observe: between 1 and {len(frames) - 1} for {len(frames)} frames, got {observe}")

    client = Client(a.url)
    first = frames[0]
    session = client.create_session(frames=[(first["image"], first["pose"])], intrinsics=cams["intrinsics"])
    for f in frames[1:observe]:
        client.observe(session, f["image"], f["pose"], depth_mm=f["depth"])
    print(f"session {session}: observed {observe} frames; generating {len(frames) - observe} at the remaining poses")

    a.out.mkdir(parents=True, exist_ok=True)
    made, truth = [], []
    for i, f in enumerate(frames[observe:], start=observe):
        step = client.step(session, {}, pose=f["pose"])
        Image.fromarray(step.image).save(a.out / f"{i:04d}.png")
        made.append(step.image)
        h, w = step.image.shape[:2]  # the session answers at your images' size
        truth.append(np.asarray(Image.fromarray(f["image"]).resize((w, h), Image.BILINEAR)))
    client.delete_session(session)

    made, truth = np.stack(made), np.stack(truth)
    held = np.asarray(Image.fromarray(frames[observe - 1]["image"]).resize(made.shape[2:0:-1], Image.BILINEAR))
    print(f"generated {len(made)} frames: PSNR {np.mean([psnr(m, t) for m, t in zip(made, truth)]):.2f} dB against your "
          f"images, sharpness {sharpness_ratio(made, truth):.2f} of theirs; the last observed frame held still: "
          f"{np.mean([psnr(held, t) for t in truth]):.2f} dB")
    columns = [np.concatenate([t, np.full((2, t.shape[1], 3), 255, np.uint8), m], axis=0)
               for t, m in list(zip(truth, made))[:: max(1, len(made) // 8)]]
    strip = np.concatenate(columns, axis=1)
    Image.fromarray(strip).resize((strip.shape[1] * 3, strip.shape[0] * 3), Image.NEAREST).save(a.out / "strip.png")
    print(f"wrote {a.out}/NNNN.png and {a.out}/strip.png (your frames on top, the generated ones below)")


if __name__ == "__main__":
    main()
