"""The synthetic world's renderer and files, checked with OpenCV and numpy.

`worldpack sim render` reports the block face under a probe pixel with its
four world corners and where the crate's camera puts them; OpenCV must put
them in the same place, and the rendered depth must be the camera z of that
face along the probe pixel's ray (computed here with cv2.undistortPoints).
"""

import json
import os
import subprocess

import cv2
import numpy as np
import pytest

BIN = os.environ.get("WORLDPACK_BIN", os.path.join(os.path.dirname(__file__), "..", "target", "release", "worldpack"))


def run(*args):
    out = subprocess.run([BIN, *args], capture_output=True, text=True, check=False)
    assert out.returncode == 0, out.stderr
    return out


def render(tmp_path, **flags):
    out = tmp_path / "frame"
    args = ["sim", "render", "--out", str(out)]
    for k, v in flags.items():
        args += [f"--{k}", str(v)]
    run(*args)
    info = json.loads((out / "render.json").read_text())
    return out, info


def opencv_camera(info):
    """OpenCV's K, rvec, tvec for the camera-to-world pose in render.json."""
    k = info["intrinsics"]
    K = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]], dtype=np.float64)
    c2w = np.array(info["camera_to_world"], dtype=np.float64)
    r_wc = c2w[:3, :3].T
    t_wc = -r_wc @ c2w[:3, 3]
    rvec, _ = cv2.Rodrigues(r_wc)
    return K, rvec, t_wc, c2w


CASES = [
    # Looking down at the ground from the spawn point, at three sizes.
    {"seed": 3, "pitch": 35.0, "yaw": 20.0, "size": "64x64", "probe": None},
    {"seed": 3, "pitch": 50.0, "yaw": -130.0, "size": "224x224", "probe": "40,170"},
    {"seed": 11, "pitch": 20.0, "yaw": 75.0, "size": "640x360", "probe": "500,300"},
]


@pytest.mark.parametrize("case", CASES)
def test_block_corners_and_depth_agree_with_opencv(tmp_path, case):
    # First find the spawn point's eye position, then look down from it.
    _, spawn = render(tmp_path, seed=case["seed"])
    p = spawn["pose5"]
    flags = {"seed": case["seed"], "size": case["size"], "pose": f"{p['x']},{p['y']},{p['z']},{case['pitch']},{case['yaw']}"}
    if case["probe"]:
        flags["probe"] = case["probe"]
    out, info = render(tmp_path, **flags)
    probe = info["probe"]
    assert probe["hit"], probe
    K, rvec, tvec, c2w = opencv_camera(info)

    corners = np.array(probe["corners_world"], dtype=np.float64)
    ours = np.array([c for c in probe["corners_pixels"] if c is not None])
    in_front = [i for i, c in enumerate(probe["corners_pixels"]) if c is not None]
    assert len(in_front) >= 3
    theirs, _ = cv2.projectPoints(corners[in_front], rvec, tvec, K, None)
    np.testing.assert_allclose(ours, theirs.reshape(-1, 2), atol=1e-6)

    # The probe pixel's ray, by OpenCV, meets the face plane at camera z = depth.
    u, v = probe["pixel"]
    ray = cv2.undistortPoints(np.array([[[u, v]]], dtype=np.float64), K, None).reshape(2)
    d_cam = np.array([ray[0], ray[1], 1.0])
    d_world = c2w[:3, :3] @ d_cam
    axis = "xyz".index(probe["face_axis"])
    plane = corners[0, axis]
    z = (plane - c2w[axis, 3]) / d_world[axis]
    depth = np.load(out / "depth.npy")
    h, w = (int(s) for s in case["size"].split("x")[::-1])
    assert depth.shape == (h, w) and depth.dtype == np.float32
    assert depth[v, u] == pytest.approx(z, rel=1e-5)
    assert probe["depth"] == pytest.approx(z, rel=1e-9)
    # The hit point lies on the reported face, inside its square.
    hit = c2w[:3, 3] + z * d_world
    others = [a for a in range(3) if a != axis]
    lo, hi = corners[:, others].min(0), corners[:, others].max(0)
    assert np.all(hit[others] >= lo - 1e-9) and np.all(hit[others] <= hi + 1e-9)


def test_every_depth_pixel_lies_on_a_block_face(tmp_path):
    """Unprojecting each pixel with its depth lands on a grid plane: one world
    coordinate is a whole number (blocks are unit cubes)."""
    _, spawn = render(tmp_path, seed=5)
    p = spawn["pose5"]
    out, info = render(tmp_path, seed=5, size="96x72", pose=f"{p['x']},{p['y']},{p['z']},15,40")
    K, _, _, c2w = opencv_camera(info)
    depth = np.load(out / "depth.npy")
    vs, us = np.nonzero(np.isfinite(depth))
    assert len(us) > 1000
    pix = np.stack([us, vs], 1).astype(np.float64).reshape(-1, 1, 2)
    rays = cv2.undistortPoints(pix, K, None).reshape(-1, 2)
    cam = np.column_stack([rays, np.ones(len(rays))]) * depth[vs, us, None].astype(np.float64)
    world = cam @ c2w[:3, :3].T + c2w[:3, 3]
    off_grid = np.abs(world - np.round(world)).min(1)
    assert off_grid.max() < 1e-3, off_grid.max()
    assert np.all(np.isinf(depth[~np.isfinite(depth)]))


def test_a_suite_reads_with_numpy_alone(tmp_path):
    out = tmp_path / "suite"
    run("sim", "loopnav", "--per-cell", "1", "--ranges", "5", "--out", str(out))
    index = json.loads((out / "index.json").read_text())
    assert index["format"] == "worldpack-suite/1" and len(index["trajectories"]) == 2
    for entry in index["trajectories"]:
        d = out / entry["dir"]
        meta = json.loads((d / "meta.json").read_text())
        n, r = meta["frames"], meta["returning_point"]
        rgb, depth = np.load(d / "rgb.npy"), np.load(d / "depth.npy")
        poses, pose5 = np.load(d / "poses.npy"), np.load(d / "pose5.npy")
        actions, phase = np.load(d / "actions.npy"), np.load(d / "phase.npy")
        assert rgb.shape == (n, 64, 64, 3) and rgb.dtype == np.uint8
        assert depth.shape == (n, 64, 64) and depth.dtype == np.uint16
        assert poses.shape == (n, 4, 4) and pose5.shape == (n, 5) and actions.shape == (n, 7)
        assert phase.shape == (n,) and set(phase[r:]) == {2} and 2 not in set(phase[:r])
        # Rotations are proper, camera centres are the 5-D eye positions.
        rot = poses[:, :3, :3]
        np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-12)
        np.testing.assert_allclose(poses[:, :3, 3], pose5[:, :3])
        # Minecraft yaw 0 faces +z, positive pitch looks down: forward is
        # (-sin yaw cos pitch, -sin pitch, cos yaw cos pitch).
        pitch, yaw = np.radians(pose5[:, 3]), np.radians(pose5[:, 4])
        forward = np.column_stack([-np.sin(yaw) * np.cos(pitch), -np.sin(pitch), np.cos(yaw) * np.cos(pitch)])
        np.testing.assert_allclose(poses[:, :3, 2], forward, atol=1e-12)
        # Each action's yaw delta is the change of yaw between frames.
        dyaw = (np.diff(pose5[:, 4]) + 180.0) % 360.0 - 180.0
        np.testing.assert_allclose(dyaw, actions[1:, 5], atol=1e-4)
        # The walk ends back at A, where it started.
        np.testing.assert_allclose(pose5[-1, [0, 2]], pose5[0, [0, 2]], atol=0.2)
