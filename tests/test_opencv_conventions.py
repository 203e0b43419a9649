"""The memory crate's pose and camera conventions, checked against OpenCV.

Every Rust computation goes through `worldpack geometry` (JSON in, JSON out);
OpenCV is the independent implementation it must agree with.
"""

import json
import math
import os
import subprocess

import cv2
import numpy as np
import pytest

BIN = os.environ.get("WORLDPACK_BIN", os.path.join(os.path.dirname(__file__), "..", "target", "release", "worldpack"))


def geometry(requests):
    """Runs a batch of requests; returns the answers (errors included)."""
    out = subprocess.run([BIN, "geometry"], input=json.dumps(requests), capture_output=True, text=True, check=False)
    assert out.stdout, out.stderr
    return json.loads(out.stdout)


def ok(answers):
    for a in answers:
        assert "error" not in a, a
    return answers


def camera_matrix(k):
    return np.array([[k["fx"], 0, k["cx"]], [0, k["fy"], k["cy"]], [0, 0, 1]], dtype=np.float64)


def random_extrinsics(rng):
    rvec = rng.normal(size=3)
    rvec *= rng.uniform(0.0, math.pi) / np.linalg.norm(rvec)
    return rvec, rng.normal(scale=5.0, size=3)


def points_in_front(rng, rvec, tvec, n):
    """World points that lie 1–20 units in front of the camera."""
    cam = np.column_stack([rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), np.ones(n)]) * rng.uniform(1, 20, (n, 1))
    r, _ = cv2.Rodrigues(rvec)
    return (r.T @ (cam - tvec).T).T


INTRINSICS = {"fx": 211.3, "fy": 198.7, "cx": 110.2, "cy": 97.9, "width": 224, "height": 200}


def test_project_points_matches_cv2():
    rng = np.random.default_rng(1)
    requests, expected = [], []
    for _ in range(40):
        rvec, tvec = random_extrinsics(rng)
        pts = points_in_front(rng, rvec, tvec, 25)
        requests.append({"op": "project", "pose": {"opencv": {"rvec": rvec.tolist(), "tvec": tvec.tolist()}},
                         "intrinsics": INTRINSICS, "points": pts.tolist()})
        px, _ = cv2.projectPoints(pts, rvec, tvec, camera_matrix(INTRINSICS), None)
        expected.append(px.reshape(-1, 2))
    for answer, want in zip(ok(geometry(requests)), expected):
        got = np.array(answer["pixels"], dtype=np.float64)
        np.testing.assert_allclose(got, want, rtol=1e-6, atol=1e-6)


def test_rodrigues_matches_cv2_both_ways():
    rng = np.random.default_rng(2)
    cases = [random_extrinsics(rng) for _ in range(50)]
    cases.append((np.array([0.0, math.pi, 0.0]), np.zeros(3)))  # half turn
    cases.append((np.zeros(3), np.zeros(3)))
    answers = ok(geometry([{"op": "convert", "pose": {"opencv": {"rvec": r.tolist(), "tvec": t.tolist()}}}
                           for r, t in cases]))
    for (rvec, tvec), a in zip(cases, answers):
        r_wc, _ = cv2.Rodrigues(rvec)
        c2w = np.array(a["c2w"]["rotation"])
        np.testing.assert_allclose(c2w, r_wc.T, atol=1e-12)
        np.testing.assert_allclose(a["c2w"]["position"], -r_wc.T @ tvec, atol=1e-9)
        # Our rvec may differ from the input by 2π wraps, but must give the same matrix.
        back, _ = cv2.Rodrigues(np.array(a["opencv"]["rvec"]))
        np.testing.assert_allclose(back, r_wc, atol=1e-9)


def test_solvepnp_recovers_the_crates_pose():
    rng = np.random.default_rng(3)
    poses = [{"pose5": {"x": float(rng.uniform(-50, 50)), "y": float(rng.uniform(60, 80)), "z": float(rng.uniform(-50, 50)),
                        "pitch": float(rng.uniform(-60, 60)), "yaw": float(rng.uniform(-180, 180)),
                        "convention": "minecraft", "unit": "degrees"}} for _ in range(20)]
    converted = ok(geometry([{"op": "convert", "pose": p} for p in poses]))
    for pose, conv in zip(poses, converted):
        r = np.array(conv["c2w"]["rotation"])
        c = np.array(conv["c2w"]["position"])
        cam = np.column_stack([rng.uniform(-0.5, 0.5, 30), rng.uniform(-0.5, 0.5, 30), np.ones(30)]) * rng.uniform(2, 25, (30, 1))
        world = (r @ cam.T).T + c
        pixels = np.array(ok(geometry([{"op": "project", "pose": pose, "intrinsics": INTRINSICS,
                                        "points": world.tolist()}]))[0]["pixels"])
        found, rvec, tvec = cv2.solvePnP(world, pixels, camera_matrix(INTRINSICS), None, flags=cv2.SOLVEPNP_ITERATIVE)
        assert found
        back = ok(geometry([{"op": "convert", "pose": {"opencv": {"rvec": rvec.ravel().tolist(), "tvec": tvec.ravel().tolist()}}}]))[0]
        np.testing.assert_allclose(back["c2w"]["rotation"], r, atol=1e-6)
        np.testing.assert_allclose(back["c2w"]["position"], c, atol=1e-5)
        assert back["minecraft"]["yaw"] == pytest.approx(pose["pose5"]["yaw"], abs=1e-5)
        assert back["minecraft"]["pitch"] == pytest.approx(pose["pose5"]["pitch"], abs=1e-5)


def pixel_of(pose5, world_point, width=64, height=64):
    """Where OpenCV itself projects a world point seen from a 5-D pose."""
    a = ok(geometry([{"op": "convert", "pose": {"pose5": pose5}}]))[0]
    k = {"fx": 32.0, "fy": 32.0, "cx": (width - 1) / 2, "cy": (height - 1) / 2}
    px, _ = cv2.projectPoints(np.array([world_point], dtype=np.float64), np.array(a["opencv"]["rvec"]),
                              np.array(a["opencv"]["tvec"]), camera_matrix(k), None)
    return px.ravel()


def p5(pitch, yaw, convention="minecraft", unit="degrees"):
    return {"x": 0.0, "y": 0.0, "z": 0.0, "pitch": pitch, "yaw": yaw, "convention": convention, "unit": unit}


CENTRE = np.array([31.5, 31.5])


@pytest.mark.parametrize(
    "pose5,looks_at",
    [
        (p5(0, 0), (0, 0, 5)),  # Minecraft yaw 0: south (+z)
        (p5(0, 90), (-5, 0, 0)),  # yaw 90: west (−x)
        (p5(0, 180), (0, 0, -5)),  # yaw 180: north
        (p5(90, 0), (0, -5, 0)),  # pitch +90: straight down
        (p5(0, 0, "mineflayer", "radians"), (0, 0, -5)),  # mineflayer yaw 0: north
        (p5(0, math.pi / 2, "mineflayer", "radians"), (-5, 0, 0)),  # mineflayer π/2: west
        (p5(0.5, 0, "mineflayer", "radians"), (0, 5 * math.tan(0.5), -5)),  # mineflayer pitch up
        (p5(0, 90, "worldmem"), (5, 0, 0)),  # WorldMem's matrix: yaw 90 faces +x
        (p5(30, 0, "worldmem"), (0, -5 * math.tan(math.radians(30)), 5)),  # its positive pitch looks down
    ],
)
def test_5d_conventions_look_where_documented(pose5, looks_at):
    np.testing.assert_allclose(pixel_of(pose5, looks_at), CENTRE, atol=1e-9)


def test_5d_image_axes_follow_the_world():
    # Facing south with y up: west (−x) is on the right of the image, up is the top.
    right = pixel_of(p5(0, 0), (-1, 0, 5))
    up = pixel_of(p5(0, 0), (0, 1, 5))
    assert right[0] > CENTRE[0] and abs(right[1] - CENTRE[1]) < 1e-9
    assert up[1] < CENTRE[1] and abs(up[0] - CENTRE[0]) < 1e-9


def test_frustum_corners_project_to_the_outer_pixel_edges():
    k = {"hfov_deg": 80.0, "vfov_deg": 60.0, "width": 64, "height": 48, "near": 0.5, "far": 20.0}
    rvec, tvec = np.array([0.1, -0.4, 0.2]), np.array([1.0, 2.0, 3.0])
    pose = {"opencv": {"rvec": rvec.tolist(), "tvec": tvec.tolist()}}
    f, = ok(geometry([{"op": "frustum", "pose": pose, "intrinsics": k}]))
    kk, = ok(geometry([{"op": "resize", "intrinsics": k, "width": 64, "height": 48}]))
    px, _ = cv2.projectPoints(np.array(f["corners"]), rvec, tvec, camera_matrix(kk), None)
    edges = np.array([[-0.5, -0.5], [63.5, -0.5], [63.5, 47.5], [-0.5, 47.5]])
    np.testing.assert_allclose(px.reshape(-1, 2), np.vstack([edges, edges]), atol=1e-9)
    h = 2 * math.tan(math.radians(40)) * 2 * math.tan(math.radians(30))
    assert f["volume"] == pytest.approx(h * (20 ** 3 - 0.5 ** 3) / 3, rel=1e-12)


def blob_centroid(image):
    m = cv2.moments(image.astype(np.float64))
    return np.array([m["m10"] / m["m00"], m["m01"] / m["m00"]])


def gaussian_blob(width, height, centre, sigma):
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    return np.exp(-((u - centre[0]) ** 2 + (v - centre[1]) ** 2) / (2 * sigma ** 2))


@pytest.mark.parametrize("size,new_size,interp", [((256, 192), (64, 48), cv2.INTER_AREA),
                                                   ((64, 48), (160, 120), cv2.INTER_LINEAR)])
def test_resizing_rescales_intrinsics_as_cv2_resize_samples(size, new_size, interp):
    (w, h), (w2, h2) = size, new_size
    k = {"fx": 0.9 * w, "fy": 0.9 * w, "cx": 0.45 * w, "cy": 0.55 * h, "width": w, "height": h}
    point = [0.4, -0.3, 3.0]
    identity = {"c2w": {"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 1]], "position": [0, 0, 0]}}
    resized, before = ok(geometry([
        {"op": "resize", "intrinsics": k, "width": w2, "height": h2},
        {"op": "project", "pose": identity, "intrinsics": k, "points": [point]},
    ]))
    src_uv = np.array(before["pixels"][0])
    image = gaussian_blob(w, h, src_uv, sigma=0.04 * w)
    small = cv2.resize(image, (w2, h2), interpolation=interp)
    after = ok(geometry([{"op": "project", "pose": identity,
                          "intrinsics": {k2: resized[k2] for k2 in ("fx", "fy", "cx", "cy", "width", "height")},
                          "points": [point]}]))[0]
    np.testing.assert_allclose(blob_centroid(small), after["pixels"][0], atol=0.02)
    # And the naive rule (scale cx without the half-pixel shift) would be visibly off.
    naive = np.array([k["cx"] * w2 / w, k["cy"] * h2 / h]) + (np.array(after["pixels"][0]) - [resized["cx"], resized["cy"]])
    assert np.abs(blob_centroid(small) - naive).max() > 0.1


def test_exact_overlap_matches_an_opencv_monte_carlo():
    """Membership tested by cv2.projectPoints: an independent check of the clipper."""
    rng = np.random.default_rng(4)
    k = {"hfov_deg": 90.0, "vfov_deg": 70.0, "width": 64, "height": 48, "near": 0.1, "far": 30.0}
    kk, = ok(geometry([{"op": "resize", "intrinsics": k, "width": 64, "height": 48}]))
    checked = 0
    for _ in range(12):
        q_rvec, q_tvec = random_extrinsics(rng)
        q_c = -cv2.Rodrigues(q_rvec)[0].T @ q_tvec
        c_rvec, _ = random_extrinsics(rng)
        # Put the candidate near the query so that overlaps are partial.
        c_pos = q_c + rng.normal(scale=6.0, size=3)
        c_tvec = -cv2.Rodrigues(c_rvec)[0] @ c_pos
        view = lambda r, t: {"pose": {"opencv": {"rvec": r.tolist(), "tvec": t.tolist()}}, "intrinsics": k}
        a, = ok(geometry([{"op": "overlap", "query": view(q_rvec, q_tvec), "candidates": [view(c_rvec, c_tvec)]}]))
        exact = a["exact"][0]
        # Uniform points in the query frustum (density ∝ z²), in its camera frame.
        n = 100_000
        z = np.cbrt(0.1 ** 3 + rng.uniform(size=n) * (30.0 ** 3 - 0.1 ** 3))
        uv = np.column_stack([rng.uniform(-0.5, 63.5, n), rng.uniform(-0.5, 47.5, n)])
        cam = np.column_stack([(uv[:, 0] - kk["cx"]) / kk["fx"] * z, (uv[:, 1] - kk["cy"]) / kk["fy"] * z, z])
        rq = cv2.Rodrigues(q_rvec)[0]
        world = (rq.T @ (cam - q_tvec).T).T
        rc = cv2.Rodrigues(c_rvec)[0]
        depth = (rc @ world.T).T[:, 2] + c_tvec[2]
        px, _ = cv2.projectPoints(world, c_rvec, c_tvec, camera_matrix(kk), None)
        px = px.reshape(-1, 2)
        inside = (depth >= 0.1) & (depth <= 30.0) & (px[:, 0] >= -0.5) & (px[:, 0] <= 63.5) & (px[:, 1] >= -0.5) & (px[:, 1] <= 47.5)
        estimate = inside.mean()
        sigma = math.sqrt(max(exact * (1 - exact), 1e-12) / n)
        assert abs(estimate - exact) <= 4 * sigma + 1 / n, (exact, estimate)
        checked += 0.02 < exact < 0.98
    assert checked >= 4


def test_bad_input_names_the_field_and_fails_the_command():
    requests = [
        {"op": "convert", "pose": {"c2w": {"rotation": [[1, 0, 0], [0, 1, 0], [0, 0, -1]], "position": [0, 0, 0]}}},
        {"op": "resize", "intrinsics": {"hfov_deg": 180, "width": 64, "height": 64}, "width": 32, "height": 32},
        {"op": "overlap", "query": {"pose": {"opencv": {"rvec": [0, 0, 0], "tvec": [0, 0, 0]}},
                                    "intrinsics": {"fx": -1, "width": 8, "height": 8}}, "candidates": []},
    ]
    out = subprocess.run([BIN, "geometry"], input=json.dumps(requests), capture_output=True, text=True)
    assert out.returncode == 2
    fields = [a["error"]["field"] for a in json.loads(out.stdout)]
    assert fields == ["pose.rotation", "intrinsics.hfov_deg", "query.intrinsics.fx"]
    # NaN is not JSON: refused as a whole with a message, not a crash.
    out = subprocess.run([BIN, "geometry"], input='{"op": "convert", "pose": {"opencv": {"rvec": [NaN, 0, 0], "tvec": [0, 0, 0]}}}',
                         capture_output=True, text=True)
    assert out.returncode == 2 and "not valid JSON" in out.stderr
