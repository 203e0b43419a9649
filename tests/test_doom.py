"""Doom through ViZDoom (docs/doom.md): the tool's pose convention against the
engine's own frames, warped by the project's warp (`worldpack geometry`, op
`warp`, which is model::warp), OpenCV's projection of Doom points against the
project's, and the dataset checker on a Doom suite and on broken copies."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from worldpack_train.metrics import psnr

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "doom"))
from worldpack_doom import engine as E  # noqa: E402
from worldpack_doom import suite as S  # noqa: E402
from worldpack_doom.walk import Geometry, heading_vector, start_points  # noqa: E402
from test_opencv_conventions import geometry as run_geometry, ok  # noqa: E402
from test_python_client import start  # noqa: E402

BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))


def geometry(requests):
    return ok(run_geometry(requests))


def c2w_input(m):
    return {"c2w": {"rotation": m[:3, :3].tolist(), "position": m[:3, 3].tolist()}}


@pytest.fixture(scope="module")
def pairs():
    """Twelve pairs of frames on MAP16: B a short step ahead of A and turned up to 20 degrees."""
    engine = E.Engine("MAP16")
    try:
        rng = np.random.default_rng(7)
        out = []
        for start, angle in start_points(engine.sectors(), Geometry(engine.sectors()), 12, rng):
            b = start + rng.uniform(16, 48) * heading_vector(angle)
            out.append((engine.view_at(*start, angle), engine.view_at(*b, angle + rng.uniform(-20, 20))))
        assert len(out) == 12
        return out
    finally:
        engine.close()


def as_world(view, convention):
    """The view's camera-to-world under the tool's convention or a deliberately wrong one."""
    if convention == "yaw flipped":
        return E.map_to_world(E.camera_to_map(view.x, view.y, view.z_eye, -view.angle))
    if convention == "up flipped":  # the camera's up axis pointing down (rolled half a turn)
        return E.map_to_world(view.c2m() @ np.diag([-1.0, -1.0, 1.0, 1.0]))
    return E.map_to_world(view.c2m())


def warp_psnr(pairs, convention, fov_offset_deg=0.0):
    """PSNR of B against A warped into B on the pixels the warp covers, pooled over the pairs."""
    k = S.intrinsics()
    if fov_offset_deg:
        hfov = np.degrees(2 * np.arctan(k["width"] / 2 / k["fx"])) + fov_offset_deg
        k["fx"] = k["fy"] = k["width"] / 2 / np.tan(np.radians(hfov) / 2)
    requests, truths = [], []
    for a, b in pairs:
        (rgb_a, depth_a), (rgb_b, _) = S.to_frame(a), S.to_frame(b)
        requests.append({"op": "warp", "target": c2w_input(as_world(b, convention)),
                         "source": {"rgb": rgb_a.ravel().tolist(), "depth_mm": depth_a.ravel().tolist(),
                                    "pose": c2w_input(as_world(a, convention)), "intrinsics": k}})
        truths.append(rgb_b)
    warped, masks = [], []
    for answer, truth in zip(geometry(requests), truths):
        warped.append(np.array(answer["rgb"], np.uint8).reshape(truth.shape))
        masks.append(np.array(answer["mask"], bool).reshape(truth.shape[:2]))
        assert masks[-1].mean() > 0.2, "the warp covers almost nothing"
    return psnr(np.stack(warped), np.stack(truths), np.stack(masks))


def test_the_documented_convention_warps_doom_frames_best(pairs):
    # Measured when this test was written (12 pairs): 27.7 dB with the convention,
    # 19.1 with the yaw flipped, 18.8 with the up axis flipped, 23.8 with the FoV
    # 10 degrees too wide; the margins asked for are half of those gaps or less.
    true = warp_psnr(pairs, "documented")
    assert true > 24.0
    assert true - warp_psnr(pairs, "yaw flipped") >= 4.0
    assert true - warp_psnr(pairs, "up flipped") >= 4.0
    assert true - warp_psnr(pairs, "documented", fov_offset_deg=10.0) >= 1.5
    assert true - warp_psnr(pairs, "documented", fov_offset_deg=-10.0) >= 1.5


def test_opencv_projects_doom_points_where_the_project_does(pairs):
    k = S.intrinsics()
    K = np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1.0]])
    rng = np.random.default_rng(3)
    for view, _ in pairs[:6]:
        c2w = E.map_to_world(view.c2m())
        # Map points in front of the camera (map units, z up), as world points.
        ahead = heading_vector(view.angle)
        side = np.array([-ahead[1], ahead[0]])
        pts_map = [np.array([view.x, view.y]) + rng.uniform(40, 400) * ahead + rng.uniform(-150, 150) * side for _ in range(20)]
        pts_map = np.array([[p[0], p[1], view.z_eye + rng.uniform(-60, 60)] for p in pts_map])
        world = (E.MAP_TO_WORLD @ pts_map.T).T / E.UNITS_PER_METRE
        answer = geometry([{"op": "project", "pose": c2w_input(c2w), "intrinsics": k, "points": world.tolist()}])[0]
        w2c = np.linalg.inv(c2w)
        rvec, _ = cv2.Rodrigues(w2c[:3, :3])
        cv_pixels, _ = cv2.projectPoints(world, rvec, w2c[:3, 3], K, None)
        ours = np.array([p if p is not None else [np.nan, np.nan] for p in answer["pixels"]], float)
        assert np.all(np.isfinite(ours)), "points ahead of the camera must project"
        np.testing.assert_allclose(ours, cv_pixels.reshape(-1, 2), atol=1e-4)  # OpenCV projects in float32
        # A point straight ahead at eye height lands on the principal point.
        centre = (E.MAP_TO_WORLD @ np.array([view.x + 100 * ahead[0], view.y + 100 * ahead[1], view.z_eye])) / E.UNITS_PER_METRE
        px = geometry([{"op": "project", "pose": c2w_input(c2w), "intrinsics": k, "points": [centre.tolist()]}])[0]["pixels"][0]
        np.testing.assert_allclose(px, [k["cx"], k["cy"]], atol=1e-6)


@pytest.fixture(scope="module")
def doom_suite(tmp_path_factory):
    out = tmp_path_factory.mktemp("doom") / "suite"
    subprocess.run([sys.executable, "-m", "worldpack_doom", "suite", "--split", "test", "--maps", "MAP20", "--count", "2",
                    "--ranges", "4", "--seed", "1", "--out", str(out)], cwd=ROOT / "doom", check=True, capture_output=True)
    return out


def check(folder):
    return subprocess.run([BIN, "check", "--data", str(folder)], capture_output=True, text=True)


def test_a_doom_suite_passes_the_checker_and_reads_like_any_suite(doom_suite):
    out = check(doom_suite)
    assert out.returncode == 0, out.stderr
    assert "2 trajectories" in out.stdout and "64x64" in out.stdout
    index = json.loads((doom_suite / "index.json").read_text())
    assert index["format"] == "worldpack-suite/1" and index["kind"] == "doom"
    for entry in index["trajectories"]:
        d = doom_suite / entry["dir"]
        phase, actions = np.load(d / "phase.npy"), np.load(d / "actions.npy")
        poses = np.load(d / "poses.npy")
        # The way back retraces the exploration: its last frame stands where the look-around did.
        np.testing.assert_allclose(poses[-1][:3, 3], poses[0][:3, 3], atol=0.05)
        assert phase[entry["returning_point"]] == 2 and phase[entry["returning_point"] - 1] == 1
        # Every walking step moves 0.216 m (motion::WALK_SPEED) within the teleport's rounding.
        steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
        walked = actions[1:, 0] == 1
        assert np.all(np.abs(steps[walked] - 0.216) < 0.05) and np.all(steps[~walked] < 0.05)


def test_an_abca_walk_comes_back_to_a_by_another_way(tmp_path):
    out = tmp_path / "abca"
    subprocess.run([sys.executable, "-m", "worldpack_doom", "suite", "--split", "test", "--maps", "MAP20", "--task", "abca",
                    "--count", "1", "--ranges", "4", "--seed", "1", "--out", str(out)], cwd=ROOT / "doom", check=True, capture_output=True)
    assert check(out).returncode == 0
    entry = json.loads((out / "index.json").read_text())["trajectories"][0]
    assert entry["task"] == "abca"
    poses = np.load(out / entry["dir"] / "poses.npy")[:, :3, 3]
    back, before = poses[entry["returning_point"]:], poses[:entry["returning_point"]]
    # It ends within a metre of A, and the way back is not the way out: its
    # middle stands at least a metre from every point walked before.
    assert np.linalg.norm(back[-1] - poses[0]) < 1.0
    middle = back[len(back) // 2]
    assert np.linalg.norm(before - middle, axis=1).min() > 1.0


@pytest.mark.parametrize("breakage, names", [
    ("meta-intrinsics", ["meta.json", "intrinsics"]),
    ("index-returning-point", ["index.json", "returning_point"]),
    ("poses-not-rotation", ["poses.npy", "frame 3"]),
    ("rgb-shape", ["rgb.npy", "shape"]),
    ("format-version", ["index.json", "format"]),
])
def test_the_checker_names_the_file_and_field_of_a_broken_folder(doom_suite, tmp_path, breakage, names):
    broken = tmp_path / "broken"
    shutil.copytree(doom_suite, broken)
    index = json.loads((broken / "index.json").read_text())
    first = broken / index["trajectories"][0]["dir"]
    if breakage == "meta-intrinsics":
        meta = json.loads((first / "meta.json").read_text())
        del meta["intrinsics"]["fx"]
        (first / "meta.json").write_text(json.dumps(meta))
    elif breakage == "index-returning-point":
        index["trajectories"][0]["returning_point"] = 10_000
        (broken / "index.json").write_text(json.dumps(index))
    elif breakage == "poses-not-rotation":
        poses = np.load(first / "poses.npy")
        poses[3, :3, :3] *= 2.0
        np.save(first / "poses.npy", poses)
    elif breakage == "rgb-shape":
        np.save(first / "rgb.npy", np.load(first / "rgb.npy")[:, :32])
    elif breakage == "format-version":
        index["format"] = "worldpack-suite/9"
        (broken / "index.json").write_text(json.dumps(index))
    out = check(broken)
    assert out.returncode != 0
    for name in names:
        assert name in out.stderr, out.stderr


def test_the_doom_walk_example_runs_against_a_real_server(tmp_path):
    """clients/python/examples/doom_walk.py, shortened to three generated frames,
    against `worldpack serve` with the committed Doom model as scripts/serve.sh serves it."""
    server, url = start(tmp_path, "--model", str(ROOT / "fixtures" / "doom" / "geometry_fused"), "--policy", "worldpack",
                        "--method", "ddim", "--steps", "4", "--covisible")
    try:
        picture = tmp_path / "walk.png"
        out = subprocess.run([sys.executable, str(ROOT / "clients" / "python" / "examples" / "doom_walk.py"), "--url", url,
                              "--max-return", "3", "--every", "1", "--range", "4", "--out", str(picture)],
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stdout + out.stderr
        frames = [line for line in out.stdout.splitlines() if line.startswith("frame ")]
        assert len(frames) == 3, out.stdout
        psnrs = [float(line.split("PSNR")[1].split("dB")[0]) for line in frames]
        assert all(5.0 < p < 60.0 for p in psnrs), psnrs
        assert "way back: 3 frames" in out.stdout and picture.stat().st_size > 1000
    finally:
        server.terminate()
        server.wait(timeout=30)


def test_the_planning_example_plans_in_doom_against_a_real_server(tmp_path):
    """clients/python/examples/plan_to_goal.py --world doom: two short episodes (the goal
    seen on the way out, and not) planned over the served Doom model's imagined futures,
    each action taken in ViZDoom and observed with its depth."""
    import json

    server, url = start(tmp_path, "--model", str(ROOT / "fixtures" / "doom" / "geometry_fused"))
    try:
        out = subprocess.run([sys.executable, str(ROOT / "clients" / "python" / "examples" / "plan_to_goal.py"), "--world", "doom",
                              "--url", url, "--episodes", "2", "--max-steps", "2", "--out-steps", "2", "--search", "all",
                              "--horizon", "1", "--out", str(tmp_path / "doom.json")],
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stdout + out.stderr
        run = json.loads((tmp_path / "doom.json").read_text())
        assert [e["goal_seen"] for e in run["episodes"]] == [True, False]
        for e, turned in zip(run["episodes"], (0.0, 180.0)):
            # Two steps out from A: the goal, A's view (seen) or A's view turned round (unseen), 0.43 m away.
            assert e["start_distance"] == pytest.approx(0.432, abs=0.01) and e["start_deg"] == pytest.approx(turned, abs=0.5), e
            assert e["steps"] <= 2 and 5.0 < e["final_psnr_db"] <= 100.0, e
    finally:
        server.terminate()
        server.wait(timeout=30)



def test_the_planner_imagines_its_candidates_at_its_own_eye_height(tmp_path):
    """The Doom planner dead-reckons its candidates' poses; they must stand on the floor it
    stands on. Episode 1 (MAP29) starts on a floor far from the map's zero: drawn at the
    standard eye height over zero, staying put imagined the present view at 20.8 dB."""
    import argparse
    import importlib.util

    from worldpack_client import Client

    spec = importlib.util.spec_from_file_location("plan_to_goal", ROOT / "clients" / "python" / "examples" / "plan_to_goal.py")
    plan = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(plan)
    server, url = start(tmp_path, "--model", str(ROOT / "fixtures" / "doom" / "geometry_fused"))
    world = plan.DoomWorld(Client(url), argparse.Namespace(stop="stay", out_steps=6, seed=0, score="psnr", sampler_steps=None))
    try:
        s, _, _, view, _ = world.start(1, False, np.random.default_rng(101))
        stay = world.actions.index(plan.STAY)
        imagined = world.imagine(s, np.array([[stay]]), view).rollouts[0].goal["psnr_db"]
        assert imagined > 33.0, imagined
    finally:
        world.close()
        server.terminate()
        server.wait(timeout=30)

def test_the_engine_turns_to_the_angle_asked_for_from_the_first_view():
    """A turn asked for in the first tics after a map loads once did not take (the view
    stayed at the spawn angle): `view_at` turns until the engine reports the angle."""
    engine = E.Engine("MAP01", seed=0)
    try:
        x, y, *_ = engine.state()
        for angle in (0.0, 45.0, 200.0):
            assert abs((engine.view_at(x, y, angle).angle - angle + 180.0) % 360.0 - 180.0) < 0.5
    finally:
        engine.close()


def test_a_suite_at_224_keeps_the_camera_and_passes_the_checker(tmp_path):
    out = tmp_path / "big"
    subprocess.run([sys.executable, "-m", "worldpack_doom", "suite", "--split", "test", "--maps", "MAP20", "--count", "1",
                    "--ranges", "4", "--seed", "1", "--size", "224", "--out", str(out)], cwd=ROOT / "doom", check=True, capture_output=True)
    checked = check(out)
    assert checked.returncode == 0 and "224x224" in checked.stdout, checked.stdout + checked.stderr
    entry = json.loads((out / "index.json").read_text())["trajectories"][0]
    assert np.load(out / entry["dir"] / "rgb.npy", mmap_mode="r").shape[1:] == (224, 224, 3)
    k, k64 = json.loads((out / entry["dir"] / "meta.json").read_text())["intrinsics"], S.intrinsics(64)
    # The same field of view at another size: the focal lengths scale with the side.
    assert abs(k["fx"] / 224 - k64["fx"] / 64) < 1e-9 and abs(k["fy"] / 224 - k64["fy"] / 64) < 1e-9
