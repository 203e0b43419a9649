"""Estimate every frame's pose by OpenCV visual odometry, as a robot without
ground truth would, and write them beside the true ones so that
`worldpack study --vo poses-vo.npy` can measure what estimated poses cost.

Frame to frame: ORB features, brute-force Hamming matches with a ratio test,
the previous frame's depth lifts its keypoints to 3-D, and `solvePnPRansac`
gives the motion (metric, since depth fixes the scale). Poses chain from the
true first pose, so errors accumulate as real odometry drifts. A step with
too few inliers keeps the previous step's motion (constant velocity).

The suite the study reads is 64x64; odometry needs more pixels, so it runs
on a render of the same trajectories at 224x224 (`worldpack sim loopnav
--size 224x224` with the same seed and per-cell), whose true poses must be
the same, and writes `poses-vo.npy` into the small suite's folders.

    .venv/bin/python scripts/visual_odometry.py --render data/loopnav-eval-224 --suite data/loopnav-eval
"""

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

MIN_INLIERS = 12


def intrinsics_matrix(meta):
    k = meta["intrinsics"]
    return np.array([[k["fx"], 0.0, k["cx"]], [0.0, k["fy"], k["cy"]], [0.0, 0.0, 1.0]])


def step(orb, matcher, prev, cur, depth_prev_m, k):
    """Camera motion from frame `prev` to `cur` as a 4x4 matrix taking points
    in prev's camera frame to cur's, and the inlier count (0: failed)."""
    kp1, d1 = orb.detectAndCompute(cv2.cvtColor(prev, cv2.COLOR_RGB2GRAY), None)
    kp2, d2 = orb.detectAndCompute(cv2.cvtColor(cur, cv2.COLOR_RGB2GRAY), None)
    if d1 is None or d2 is None or len(kp1) < MIN_INLIERS or len(kp2) < MIN_INLIERS:
        return None, 0
    pairs = matcher.knnMatch(d1, d2, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < 0.8 * p[1].distance]
    obj, img = [], []
    h, w = depth_prev_m.shape
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    for m in good:
        u, v = kp1[m.queryIdx].pt
        z = depth_prev_m[min(int(round(v)), h - 1), min(int(round(u)), w - 1)]
        if z <= 0:
            continue
        obj.append(((u - cx) * z / fx, (v - cy) * z / fy, z))
        img.append(kp2[m.trainIdx].pt)
    if len(obj) < MIN_INLIERS:
        return None, 0
    ok, rvec, tvec, inliers = cv2.solvePnPRansac(
        np.array(obj, np.float64), np.array(img, np.float64), k, None, iterationsCount=200, reprojectionError=2.0, flags=cv2.SOLVEPNP_ITERATIVE
    )
    if not ok or inliers is None or len(inliers) < MIN_INLIERS:
        return None, 0
    m = np.eye(4)
    m[:3, :3] = cv2.Rodrigues(rvec)[0]
    m[:3, 3] = tvec.ravel()
    return m, len(inliers)


def odometry(rgb, depth_mm, k, first_pose):
    """Camera-to-world poses (OpenCV axes) chained from `first_pose`; the
    count of steps that fell back to constant velocity."""
    orb = cv2.ORB_create(nfeatures=1500, fastThreshold=5)
    matcher = cv2.BFMatcher(cv2.NORM_HAMMING)
    poses = [first_pose]
    motion = np.eye(4)  # prev camera → current camera
    failures = 0
    for t in range(1, len(rgb)):
        m, _ = step(orb, matcher, rgb[t - 1], rgb[t], depth_mm[t - 1] / 1000.0, k)
        if m is None:
            failures += 1
        else:
            motion = m
        # c2w_t = c2w_{t-1} · (cam_{t-1} ← cam_t) = c2w_{t-1} · motion⁻¹
        poses.append(poses[-1] @ np.linalg.inv(motion))
    return np.stack(poses), failures


def rotation_deg(a, b):
    r = a[:3, :3].T @ b[:3, :3]
    return np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--render", required=True, type=Path, help="the suite rendered at 224x224 or more")
    ap.add_argument("--suite", required=True, type=Path, help="the suite the study reads (gets the estimated poses)")
    ap.add_argument("--file", default="poses-vo.npy", help="name of the poses file to write in each trajectory folder")
    ap.add_argument("--limit", type=int, help="only the first n trajectories")
    a = ap.parse_args()

    dirs = sorted(p.parent.name for p in a.suite.glob("*/meta.json"))[: a.limit]
    if not dirs:
        sys.exit(f"--suite: no trajectories in {a.suite}")
    summary = []
    for i, name in enumerate(dirs):
        src = a.render / name
        if not (src / "meta.json").exists():
            sys.exit(f"--render: {src} is missing; render the suite with the same --seed and --per-cell at 224x224")
        meta = json.loads((src / "meta.json").read_text())
        if meta["intrinsics"]["width"] < 224 or meta["intrinsics"]["height"] < 224:
            sys.exit(f"--render: {src} is {meta['intrinsics']['width']}x{meta['intrinsics']['height']}; visual odometry needs 224x224 or more")
        truth = np.load(src / "poses.npy")
        small = np.load(a.suite / name / "poses.npy")
        if truth.shape != small.shape or not np.allclose(truth, small, atol=1e-9):
            sys.exit(f"--render: {name} has other true poses than in --suite; render it with the same --seed and --per-cell")
        rgb, depth = np.load(src / "rgb.npy"), np.load(src / "depth.npy")
        est, failures = odometry(rgb, depth, intrinsics_matrix(meta), truth[0])
        np.save(a.suite / name / a.file, est)
        drift = np.linalg.norm(est[:, :3, 3] - truth[:, :3, 3], axis=1)
        rot = np.array([rotation_deg(x, y) for x, y in zip(truth, est)])
        row = {"trajectory": name, "frames": len(truth), "fallback_steps": failures,
               "mean_error_blocks": float(drift.mean()), "final_error_blocks": float(drift[-1]),
               "mean_error_deg": float(rot.mean()), "final_error_deg": float(rot[-1])}
        summary.append(row)
        print(f"[{i + 1}/{len(dirs)}] {name}: {len(truth)} frames, fallback {failures}, "
              f"error mean {row['mean_error_blocks']:.3f} blocks / {row['mean_error_deg']:.2f}°, final {row['final_error_blocks']:.3f} / {row['final_error_deg']:.2f}°", flush=True)
    out = a.suite / "visual_odometry.json"
    out.write_text(json.dumps({"render": str(a.render), "file": a.file, "trajectories": summary}, indent=1))
    print(f"wrote {a.file} into {len(dirs)} trajectories and {out}")


if __name__ == "__main__":
    main()
