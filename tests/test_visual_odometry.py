"""OpenCV visual odometry on rendered frames recovers the renderer's poses:
the pose convention (OpenCV camera-to-world, x right, y down, z forward)
and the depth unit hold end to end, and the estimated poses are what the
pose-noise study feeds back to `worldpack study --vo`."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
sys.path.insert(0, str(ROOT / "scripts"))
import visual_odometry as vo  # noqa: E402


def sim(out, size):
    args = [BIN, "sim", "loopnav", "--per-cell", "1", "--tasks", "aba", "--ranges", "5", "--seed", "4", "--size", size, "--out", str(out)]
    done = subprocess.run(args, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def suites(tmp_path_factory):
    base = tmp_path_factory.mktemp("vo")
    sim(base / "big", "224x224")
    sim(base / "small", "64x64")
    return base / "big", base / "small"


def relative(a, b):
    """b's pose in a's camera frame."""
    return np.linalg.inv(a) @ b


def test_each_step_is_recovered_to_a_fraction_of_a_degree_and_block(suites):
    big, _ = suites
    d = next(p.parent for p in big.glob("*/meta.json"))
    meta = json.loads((d / "meta.json").read_text())
    truth, rgb, depth = np.load(d / "poses.npy"), np.load(d / "rgb.npy"), np.load(d / "depth.npy")
    est, failures = vo.odometry(rgb, depth, vo.intrinsics_matrix(meta), truth[0])
    assert failures <= len(truth) // 20, f"{failures} of {len(truth)} steps fell back"
    rot_err, trans_err, moved = [], [], []
    for t in range(1, len(truth)):
        r_true, r_est = relative(truth[t - 1], truth[t]), relative(est[t - 1], est[t])
        rot_err.append(vo.rotation_deg(r_true, r_est))
        trans_err.append(np.linalg.norm(r_true[:3, 3] - r_est[:3, 3]))
        moved.append(np.linalg.norm(r_true[:3, 3]))
    # Measured on suite trajectories: median errors about 0.12° and 0.03 block per 0.22-block step.
    assert np.median(rot_err) < 0.5, np.median(rot_err)
    assert np.median(trans_err) < 0.05, np.median(trans_err)
    # Not trivially small: the camera really moves, and standing still would be far off.
    assert np.median(trans_err) < 0.25 * np.median([m for m in moved if m > 0])


def test_the_script_writes_poses_the_study_can_read(suites):
    big, small = suites
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "visual_odometry.py"), "--render", str(big), "--suite", str(small)],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    summary = json.loads((small / "visual_odometry.json").read_text())
    for row in summary["trajectories"]:
        d = small / row["trajectory"]
        est, truth = np.load(d / "poses-vo.npy"), np.load(d / "poses.npy")
        assert est.shape == truth.shape
        assert np.allclose(est[0], truth[0])
        r = est[:, :3, :3]
        assert np.allclose(r @ np.transpose(r, (0, 2, 1)), np.eye(3), atol=1e-6)
        assert 0 < row["mean_error_blocks"] < 2.0


def test_a_render_of_other_trajectories_is_refused(tmp_path, suites):
    _, small = suites
    other = tmp_path / "other"
    args = [BIN, "sim", "loopnav", "--per-cell", "1", "--tasks", "aba", "--ranges", "5", "--seed", "5", "--size", "224x224", "--out", str(other)]
    assert subprocess.run(args, capture_output=True, check=False).returncode == 0
    done = subprocess.run([sys.executable, str(ROOT / "scripts" / "visual_odometry.py"), "--render", str(other), "--suite", str(small)],
                          capture_output=True, text=True, check=False)
    assert done.returncode != 0
    assert "--render" in done.stderr
