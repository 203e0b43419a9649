"""Drive ViZDoom through a served Doom model: observe the exploration (frames,
depth, poses, intrinsics), generate the way back, and score every generated
frame against the engine's own frame at that pose.

    ./scripts/serve.sh --model fixtures/doom/geometry_fused &     # served as its manifest says
    python clients/python/examples/doom_walk.py --out doom_walk.png

Needs the Doom tool's requirements (doom/requirements.txt: vizdoom, opencv) and
the project's metrics (`pip install --no-deps -e train`: numpy only), and runs
from a checkout (it imports doom/worldpack_doom). The walk is an ABA loop
on a map no model was trained on (MAP20 by default): look around at A, walk to
B, turn round, come back along the same points.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from worldpack_client import Client
from worldpack_train.metrics import psnr

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "doom"))
from worldpack_doom import engine as E  # noqa: E402
from worldpack_doom import suite as S  # noqa: E402
from worldpack_doom.walk import Geometry, out_and_back, start_points  # noqa: E402


def ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM with an 11x11 Gaussian window (sigma 1.5) on the grey image, valid region: the metric `eval` reports."""
    g = np.exp(-((np.arange(11) - 5) ** 2) / (2 * 1.5**2))
    g /= g.sum()

    def blur(x):
        x = np.apply_along_axis(lambda r: np.convolve(r, g, mode="valid"), 1, x)
        return np.apply_along_axis(lambda c: np.convolve(c, g, mode="valid"), 0, x)

    x, y = (im.astype(np.float64) @ [0.299, 0.587, 0.114] for im in (a, b))
    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    return float(np.mean(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))))


def action(plan, t: int) -> dict:
    return {"forward": bool(plan.forward[t]), "yaw_deg": float(plan.yaw[t])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--url", default="http://127.0.0.1:8080")
    ap.add_argument("--map", default="MAP20", help="a held-out map: MAP20, MAP29 or MAP18")
    ap.add_argument("--seed", type=int, default=0, help="picks the starting point and the walk")
    ap.add_argument("--range", type=float, default=8.0, help="metres from A to B (at least 0.8 of it)")
    ap.add_argument("--policy", default=None,
                    help="the session's memory policy kind (baseline for a 4-frame model); default: the server's --policy, "
                         "with co-visibility when it runs with --covisible")
    ap.add_argument("--max-return", type=int, help="generate only this many frames of the way back")
    ap.add_argument("--every", type=int, default=6, help="one column of the picture every this many generated frames")
    ap.add_argument("--out", default="doom_walk.png")
    a = ap.parse_args()

    engine = E.Engine(a.map, seed=a.seed)
    try:
        rng = np.random.default_rng(a.seed)
        geom = Geometry(engine.sectors())
        plan = None
        for start, angle in start_points(engine.sectors(), geom, 40, rng):
            plan = out_and_back(geom, start, angle, a.range * E.UNITS_PER_METRE, rng)
            if plan is not None:
                break
        if plan is None:
            sys.exit(f"--map {a.map}: no out-and-back walk of {a.range} m found from 40 starting points")

        def seen(t):
            view = engine.view_at(*plan.points[t], plan.angles[t])
            rgb, depth = S.to_frame(view)
            return rgb, depth, E.map_to_world(view.c2m())

        client = Client(a.url)
        rgb, depth, pose = seen(0)
        session = client.create_session(frames=[(rgb, pose)], intrinsics=S.intrinsics(), policy={"kind": a.policy} if a.policy else None)
        back = plan.returning_point
        for t in range(1, back):                       # the exploration, observed with depth
            rgb, depth, pose = seen(t)
            client.observe(session, rgb, pose, depth_mm=depth, action=action(plan, t))
        print(f"{a.map}: observed {back} frames of the exploration; generating the way back")
        last_observed = rgb
        end = len(plan.points) if a.max_return is None else min(len(plan.points), back + a.max_return)
        scores, copy_scores, columns = [], [], []
        for i, t in enumerate(range(back, end)):
            truth, _, pose = seen(t)
            step = client.step(session, action(plan, t), pose=pose)
            scores.append((psnr(step.image, truth), ssim(step.image, truth)))
            copy_scores.append(psnr(last_observed, truth))
            print(f"frame {t:3d}  PSNR {scores[-1][0]:6.2f} dB  SSIM {scores[-1][1]:.3f}  "
                  f"(the last observed frame: {copy_scores[-1]:6.2f} dB)  {step.timings_ms['total']:.0f} ms")
            if i % a.every == 0:
                columns.append(np.concatenate([step.image, np.full((2, 64, 3), 255, np.uint8), truth], axis=0))
        client.delete_session(session)
    finally:
        engine.close()
    p = np.array(scores)
    print(f"way back: {len(p)} frames, PSNR {p[:, 0].mean():.2f} dB, SSIM {p[:, 1].mean():.3f} "
          f"(the last observed frame held still: {np.mean(copy_scores):.2f} dB)")
    gap = np.full((130, 2, 3), 255, np.uint8)
    strip = np.concatenate([c for col in columns for c in (col, gap)][:-1], axis=1)
    Image.fromarray(strip).resize((strip.shape[1] * 3, strip.shape[0] * 3), Image.NEAREST).save(a.out)
    print(f"wrote {a.out}: generated (top) over the engine's frame (bottom)")


if __name__ == "__main__":
    main()
