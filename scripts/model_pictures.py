"""Next-frame pictures from an exported model, with ONNX Runtime only (no torch):
for frames on the way back of held-out ABA/ABCA trajectories, the newest context
frame, the best-overlap memory (WorldPack's first slot), the model's prediction
and the truth, side by side.

    .venv/bin/python scripts/model_pictures.py --model fixtures/small \
        --data data/loopnav-mini -o docs/model/next_frames.png
"""

import argparse
import json
import pathlib

import cv2
import numpy as np
import onnxruntime as ort

ROOT = pathlib.Path(__file__).resolve().parent.parent
from worldpack_train.core import data as wdata  # torch-free
from worldpack_train.core.config import LAYOUTS, DiffusionConfig
from worldpack_train.core.diffusion import Schedule, sample
from worldpack_train.metrics import psnr


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=pathlib.Path, default=ROOT / "fixtures" / "small")
    ap.add_argument("--data", type=pathlib.Path, required=True, help="a suite with plans (worldpack plan --data ...)")
    ap.add_argument("--rows", type=int, default=6)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("-o", "--out", type=pathlib.Path, required=True)
    a = ap.parse_args()

    m = json.loads((a.model / "manifest.json").read_text())
    sess = lambda f: ort.InferenceSession(str(a.model / f), providers=["CPUExecutionProvider"])
    enc, dec = sess(m["autoencoder"]["encoder"]["file"]), sess(m["autoencoder"]["decoder"]["file"])
    lay = next(x for x in m["denoiser"]["layouts"] if x["name"] == "worldpack")
    den = sess(lay["file"])
    scale = m["autoencoder"]["latent_scale"]

    # Encode the suite's frames with the exported encoder, as the server would.
    tmp = a.out.parent / ".latents"
    tmp.mkdir(parents=True, exist_ok=True)
    dirs = wdata.trajectories(a.data)
    for d in dirs:
        rgb = wdata.to_unit_range(np.load(d / "rgb.npy"))
        z = np.concatenate([enc.run(None, {"image": c})[0] for c in np.array_split(rgb, max(1, len(rgb) // 256))])
        np.save(tmp / f"{d.name}.npy", (z * scale).astype(np.float16))
    source = wdata.PlannedLatents(a.data, tmp, "worldpack", LAYOUTS["worldpack"])
    schedule = Schedule(DiffusionConfig(**{k: m["diffusion"][k] for k in ("timesteps", "beta_start", "beta_end")}))

    def to_u8(x):
        return (np.clip((np.moveaxis(x, 0, -1) + 1) * 127.5, 0, 255)).round().astype(np.uint8)

    rows, psnr_pred, psnr_copy = [], [], []
    rng = np.random.default_rng(0)
    for i in range(min(a.rows, len(dirs))):
        t = (len(source.plans[i]) * 3) // 4
        b = source.gather([(i, t)])
        feed = {"action": b.action, "rel_time": b.rel_time}
        for r, g in zip(LAYOUTS["worldpack"].rates, b.groups):
            for key, arr in zip(("context", "context_time", "context_pose", "context_mask"), g):
                feed[f"{key}_r{r}"] = arr
        eps_fn = lambda x, tt: den.run(None, {**feed, "x_t": x, "timestep": tt})[0]
        tr = sample(eps_fn, schedule, rng.standard_normal(b.target.shape).astype(np.float32), a.steps, "ancestral", rng=rng)
        pred = dec.run(None, {"latent": tr.x[-1] / scale})[0][0]
        rgb = np.load(dirs[i] / "rgb.npy")
        ids = source.plans[i][t]
        newest = rgb[ids[ids >= 0].max()]
        best = rgb[ids[0]]
        truth = rgb[t]
        p = to_u8(pred)
        psnr_pred.append(psnr(p, truth))
        psnr_copy.append(psnr(newest, truth))
        gap = np.full((truth.shape[0], 4, 3), 255, np.uint8)
        rows.append(np.concatenate([newest, gap, best, gap, p, gap, truth], axis=1))
    sep = np.full((4, rows[0].shape[1], 3), 255, np.uint8)
    grid = np.concatenate([x for r in rows for x in (r, sep)][:-1], axis=0)
    grid = cv2.resize(grid, None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR))
    for f in tmp.iterdir():
        f.unlink()
    tmp.rmdir()
    print(f"wrote {a.out}: columns = newest context frame | best-overlap memory | prediction ({a.steps} steps) | truth")
    print(f"PSNR over {len(rows)} frames: prediction {np.mean(psnr_pred):.2f} dB, copying the newest frame {np.mean(psnr_copy):.2f} dB")


if __name__ == "__main__":
    main()
