"""Walk a LoopNav-style loop through the Gymnasium environment and save a
strip of frames: each column a step, the prediction above the world's true
frame there, with each step's PSNR in the console.

    ./scripts/serve.sh &                                  # the server, in another terminal
    python clients/python/examples/loop_walk.py --out loop.png

The loop: look around, walk out, turn back, walk the same way home (the
return leg is where memory should bring the scene back).
"""

import argparse

import numpy as np
from PIL import Image

from worldpack_client import Client
from worldpack_client.env import WorldPackEnv


def loop(out_steps: int):
    """Actions of an out-and-back walk: 12 turns of 30° (look around), out, 6 turns of 30° (about face), back."""
    look = [{"yaw_deg": 30.0}] * 12
    walk = [{"forward": 1}] * out_steps
    about = [{"yaw_deg": 30.0}] * 6
    return look + walk + about + walk


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--seed", type=int, default=3, help="the synthetic world")
    ap.add_argument("--out-steps", type=int, default=20, help="steps out (and back)")
    ap.add_argument("--every", type=int, default=4, help="one column every this many steps")
    ap.add_argument("--out", default="loop.png")
    a = ap.parse_args()

    actions = loop(a.out_steps)
    env = WorldPackEnv(Client(a.url), max_steps=len(actions))
    env.reset(seed=a.seed)
    columns, scores = [], []
    for i, action in enumerate(actions):
        full = {"forward": 0, "back": 0, "left": 0, "right": 0, "jump": 0, "yaw_deg": 0.0, "pitch_deg": 0.0, **action}
        obs, _, _, truncated, info = env.step(full)
        scores.append(info.get("psnr_db"))
        print(f"step {i + 1:3d}  frame {info['index']:3d}  PSNR {info.get('psnr_db', float('nan')):6.2f} dB  SSIM {info.get('ssim', float('nan')):.3f}")
        if (i + 1) % a.every == 0:
            truth = env.client.frame_truth(env.session, info["index"])
            columns.append(np.concatenate([obs["frame"], np.full((2, obs["frame"].shape[1], 3), 255, np.uint8), truth], axis=0))
    env.close()
    gap = np.full((columns[0].shape[0], 2, 3), 255, np.uint8)
    strip = np.concatenate(sum(([c, gap] for c in columns), [])[:-1], axis=1)
    Image.fromarray(strip).save(a.out)
    back = [s for s in scores[-a.out_steps:] if s is not None]
    print(f"wrote {a.out}: {len(columns)} columns (prediction above truth); mean PSNR on the way back {np.mean(back):.2f} dB")


if __name__ == "__main__":
    main()
