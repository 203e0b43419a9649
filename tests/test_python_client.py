"""The Python client and the Gymnasium environment (clients/python) against
a real `worldpack serve` on loopback: no mock anywhere."""

import json
import os
import socket
import subprocess
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from worldpack_client import Client, WorldPackError, c2w, opencv, opengl, pose5
from worldpack_client.env import WorldPackEnv

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))


def start(tmp, *flags, env=None, bare=False):
    """A server on a free port; the small test model unless `flags` name another or serve
    memory only (or, with `bare`, whatever `worldpack serve` serves without --model)."""
    if "--model" not in flags and "--memory-only" not in flags and not bare:
        flags = ("--model", "fixtures/small", *flags)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([BIN, "serve", "--store", str(tmp / "store.redb"), "--addr", f"127.0.0.1:{port}", *flags],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, **(env or {})})
    url = f"http://127.0.0.1:{port}"
    for _ in range(300):
        try:
            urllib.request.urlopen(url + "/v1/health", timeout=1)
            return proc, url
        except urllib.error.HTTPError:  # answering (401: it has tokens)
            return proc, url
        except OSError:
            if proc.poll() is not None:
                pytest.fail(f"the server exited: {proc.stderr.read()}")
            time.sleep(0.1)
    pytest.fail("the server did not come up")


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    proc, url = start(tmp_path_factory.mktemp("client"), "--steps", "2")
    yield url
    proc.terminate()
    proc.wait(timeout=30)


def test_a_bare_serve_serves_the_served_model_as_its_manifest_says(tmp_path):
    proc, url = start(tmp_path, bare=True)
    try:
        health = json.load(urllib.request.urlopen(url + "/v1/health"))
        assert health["model"] == "worldpack_geometry_fused_1step", health
        client = Client(url)
        session = client.create_session(synthetic_seed=3)
        step = client.step(session, {"forward": True, "yaw_deg": 6})
        # The manifest's serving block: the 1-step student, its warp chosen by co-visibility.
        assert step.raw["steps"] == 1 and step.raw["selection"]["warp_frames"], step.raw["selection"]
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_gymnasium_check_env_passes(server):
    env = WorldPackEnv(Client(server), max_steps=3)
    check_env(env, skip_render_check=False)
    env.close()


def test_the_environment_sees_and_answers_at_its_size(server):
    env = WorldPackEnv(Client(server), max_steps=2, size=(96, 96))
    assert env.observation_space["frame"].shape == (96, 96, 3)
    check_env(env, skip_render_check=False)
    obs, _ = env.reset(seed=4)
    assert obs["frame"].shape == (96, 96, 3)
    obs, *_ = env.step(env.action_space.sample())
    assert obs["frame"].shape == (96, 96, 3) and env.observation_space.contains(obs)
    env.close()
    with pytest.raises(WorldPackError) as refused:
        Client(server).create_session(synthetic_seed=4, size=4096)
    assert refused.value.field == "synthetic.size" and "--max-frame-side" in str(refused.value)


def test_every_sampled_action_is_accepted_and_episodes_truncate(server):
    env = WorldPackEnv(Client(server), max_steps=6)
    obs, info = env.reset(seed=3)
    assert obs["frame"].shape == (64, 64, 3) and obs["frame"].dtype == np.uint8
    env.action_space.seed(11)
    truncated, steps = False, 0
    while not truncated:
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        steps += 1
        assert obs["frame"].shape == (64, 64, 3) and not terminated and reward == 0.0
        assert len(info["plan"]["slots"]) == 22, "the server's default policy is WorldPack: 22 slots"
        assert 0.0 < info["psnr_db"] <= 100.0 and -1.0 <= info["ssim"] <= 1.0, "a synthetic session scores each frame"
        np.testing.assert_array_equal(env.render(), obs["frame"])
    assert steps == 6
    session = env.session
    env.close()
    with pytest.raises(WorldPackError) as e:
        env.client.session(session)
    assert e.value.status == 404 and e.value.field == "session"


def test_observed_images_and_depth_read_back_equal_in_every_pose_form(server):
    c = Client(server)
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    depth = rng.integers(0, 40000, (48, 64), dtype=np.uint16)
    identity = np.eye(4)
    session = c.create_session(frames=[(image, identity)], intrinsics={"hfov_deg": 70, "width": 64, "height": 48})
    forms = {
        "c2w": c2w(np.eye(3), [1.0, 2.0, 3.0]),
        "opencv": opencv([0.0, 0.3, 0.0], [0.5, 0.0, -2.0]),
        "opengl": opengl([[1, 0, 0, 4.0], [0, 1, 0, 5.0], [0, 0, 1, 6.0], [0, 0, 0, 1]]),
        "pose5": pose5(10.0, 64.0, -3.0, 15.0, 90.0),
        "array": np.array([[0, 0, 1, 7.0], [0, 1, 0, 0], [-1, 0, 0, 1.0], [0, 0, 0, 1]]),
    }
    for name, pose in forms.items():
        r = c.observe(session, image, pose, depth_mm=depth, action={"forward": True})
        np.testing.assert_array_equal(c.frame_image(session, r["index"]), image, err_msg=name)
        np.testing.assert_array_equal(c.frame_depth(session, r["index"]), depth, err_msg=name)
    # The array form is OpenCV camera-to-world: it reads back as given.
    back = c.frame(session, r["index"])["pose"]
    np.testing.assert_allclose(np.asarray(back["position"]), [7.0, 0.0, 1.0], atol=1e-9)
    plan = c.select(session, np.eye(4))["plan"]
    assert any(s["frame"] is not None for s in plan["slots"])


def test_bad_requests_raise_with_the_servers_field(server):
    c = Client(server)
    session = c.create_session(synthetic_seed=5)
    with pytest.raises(WorldPackError) as e:
        c.step(session, {"forward": True, "yaw_deg": 400.0})
    assert (e.value.status, e.value.field) == (400, "action.yaw_deg")
    with pytest.raises(WorldPackError) as e:
        c.observe(session, np.zeros((64, 64, 3), np.uint8), c2w(2 * np.eye(3), [0, 0, 0]))
    assert e.value.status == 400 and e.value.field.startswith("pose"), e.value
    # A step sent again after its answer was lost is refused, not taken twice.
    first = c.step(session, {"forward": True}, expected_index=1)
    with pytest.raises(WorldPackError) as e:
        c.step(session, {"forward": True}, expected_index=1)
    assert (e.value.status, e.value.field) == (409, "expected_index")
    assert c.session(session)["frames"] == first.index + 1 == 2


def test_refusals_under_load_are_retried_to_success(tmp_path):
    proc, url = start(tmp_path, "--steps", "2", "--max-queue", "1")
    try:
        c = Client(url)
        session = c.create_session(synthetic_seed=7)
        errors = []

        def slow_step():
            try:
                Client(url).step(session, {"forward": True}, steps=400, expected_index=1)
            except Exception as e:  # noqa: BLE001 - reported below
                errors.append(e)

        stepper = threading.Thread(target=slow_step)
        stepper.start()
        time.sleep(0.3)  # the step holds the session; one more request may queue, the rest are refused
        clients = [Client(url) for _ in range(4)]
        answers = [None] * 4
        threads = [threading.Thread(target=lambda i=i: answers.__setitem__(i, clients[i].select(session, np.eye(4)))) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads + [stepper]:
            t.join(timeout=300)
        assert not errors, errors
        assert all(a is not None and "plan" in a for a in answers), answers
        refusals = [r for cl in clients for r in cl.refusals]
        assert refusals, "four selects behind a slow step and a full queue: some were refused"
        assert all(r == (429, "1") for r in refusals), refusals
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_an_observing_step_records_the_worlds_frame_and_depth(server):
    c = Client(server)
    session = c.create_session(synthetic_seed=3)
    step = c.step(session, {"forward": True}, observe=True)
    assert step.raw["source"] == "observed" and step.truth is None
    depth = c.frame_depth(session, step.index)
    assert depth.shape == step.image.shape[:2] and depth.max() > 0, "the world's depth comes with the frame"
    np.testing.assert_array_equal(c.frame_image(session, step.index), step.image)
    generated = c.step(session, {"forward": True})
    assert generated.raw["source"] == "generated" and generated.truth["psnr_db"] > 0


def test_a_client_with_a_token_is_let_in_and_one_without_is_told_why(tmp_path, monkeypatch):
    proc, url = start(tmp_path, "--steps", "2", env={"WORLDPACK_TOKENS": "acme:tok-acme,beta:tok-beta"})
    try:
        monkeypatch.delenv("WORLDPACK_TOKEN", raising=False)
        with pytest.raises(WorldPackError) as e:
            Client(url).health()
        assert (e.value.status, e.value.field) == (401, "authorization")
        acme = Client(url, token="tok-acme")
        sid = acme.create_session(synthetic_seed=3)
        assert acme.step(sid, {"forward": True}).index == 1
        assert "tok-acme" not in repr(acme), "the token is never printed"
        with pytest.raises(WorldPackError) as e:
            Client(url, token="tok-beta").session(sid)
        assert (e.value.status, e.value.field) == (404, "session"), "another tenant's session is not there"
        monkeypatch.setenv("WORLDPACK_TOKEN", "tok-acme")
        env = WorldPackEnv(Client(url), max_steps=2)
        obs, _ = env.reset(seed=3)
        assert obs["frame"].shape == (64, 64, 3)
        env.close()
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_gymnasium_makes_the_environment_by_name(server):
    import gymnasium

    env = gymnasium.make("worldpack_client.env:WorldPack-v0", url=server, max_steps=2)
    obs, _ = env.reset(seed=3)
    assert obs["frame"].shape == (64, 64, 3)
    _, _, _, truncated, info = env.step(env.action_space.sample())
    assert info["index"] == 1 and not truncated
    env.close()
    same = gymnasium.make("WorldPack-v0", url=server, max_steps=1)  # registered by the import above
    assert same.unwrapped.max_steps == 1
    same.close()


def test_a_fork_shares_the_present_and_steps_apart(server):
    c = Client(server)
    parent = c.create_session(synthetic_seed=3)
    c.step(parent, {"forward": True}, seed=1)
    fork = c.fork(parent)
    info = c.session(fork)
    assert (info["frames"], info["parent"], info["forked_at"]) == (2, parent, 2)
    np.testing.assert_array_equal(c.frame_image(fork, 1), c.frame_image(parent, 1))
    a, b = c.step(parent, {"yaw_deg": 10}, seed=4), c.step(fork, {"yaw_deg": 10}, seed=4)
    np.testing.assert_array_equal(a.image, b.image)
    c.step(fork, {"left": True})
    assert (c.session(parent)["frames"], c.session(fork)["frames"]) == (3, 4)
    with pytest.raises(WorldPackError) as e:
        c.delete_session(parent)
    assert (e.value.status, e.value.field) == (409, "session"), "a session with a live fork is kept"
    c.delete_session(fork)
    c.delete_session(parent)


def test_imagine_rolls_candidates_out_and_changes_nothing(server):
    c = Client(server)
    session = c.create_session(synthetic_seed=4)
    c.step(session, {"forward": True}, observe=True)
    goal = c.frame_image(session, 0)
    plans = [[{"forward": True}, {"yaw_deg": 20}], [{"yaw_deg": -40}, {"yaw_deg": -40}], [{}, {}]]
    out = c.imagine(session, plans, seed=7, frames="all", goal=goal)
    assert out.model_calls == 2 and len(out.rollouts) == 3 and out.frames_made == 6, "three candidates apart from the first step"
    twice = c.imagine(session, [plans[0], plans[0][:1] + [{"yaw_deg": -20}]], seed=7, frames="all")
    assert twice.frames_made == 3, "one first step for two candidates that begin alike"
    np.testing.assert_array_equal(twice.rollouts[1].frames[0], twice.rollouts[0].frames[0])
    for r in out.rollouts:
        assert len(r.poses) == 2 and r.poses[0].shape == (4, 4)
        assert sorted(r.frames) == [0, 1] and r.frames[1].shape == (64, 64, 3) and r.frames[1].dtype == np.uint8
        assert r.goal["psnr_db"] > 0 and r.goal["latent_mse"] >= 0
    assert c.session(session)["frames"] == 2, "imagining stores nothing"
    latents = c.imagine(session, plans[:1], seed=7, frames=1, format="latent")
    assert latents.rollouts[0].frames[0].dtype == np.float32 and latents.rollouts[0].frames[0].ndim == 3
    # One candidate is a fork stepped with the same actions and seeds.
    fork = c.fork(session)
    for h, action in enumerate(plans[0]):
        np.testing.assert_array_equal(c.step(fork, action, seed=7 + h).image, out.rollouts[0].frames[h])
    with pytest.raises(WorldPackError) as e:
        c.imagine(session, [[{"yaw_deg": 999}]])
    assert (e.value.status, e.value.field) == (400, "candidates[0].actions[0].yaw_deg")


def test_the_environment_forks_and_imagines(server):
    env = WorldPackEnv(Client(server), max_steps=5)
    obs, _ = env.reset(seed=5)
    env.action_space.seed(3)
    env.step(env.action_space.sample())
    branch = env.fork()
    np.testing.assert_array_equal(branch.render(), env.render())
    assert (branch.index, branch.steps) == (env.index, env.steps)
    futures = env.imagine([[env.action_space.sample() for _ in range(3)] for _ in range(2)])
    assert len(futures.rollouts) == 2 and sorted(futures.rollouts[0].frames) == [2]
    a = {"forward": 1, "back": 0, "left": 0, "right": 0, "jump": 0, "yaw_deg": 5.0, "pitch_deg": 0.0}
    b = dict(a, forward=0, yaw_deg=-60.0)
    (obs_a, *_), (obs_b, *_) = env.step(a), branch.step(b)
    assert not np.array_equal(obs_a["frame"], obs_b["frame"]), "the fork's step is its own"
    assert env.client.session(env.session)["frames"] == env.index == branch.index
    branch.close()
    env.close()


def test_the_planning_example_runs_episodes_and_compares_them(server, tmp_path):
    """clients/python/examples/plan_to_goal.py end to end on the small model: a planner and
    a random policy over the same two episodes (a goal seen, a goal not), then compared."""
    import json
    import sys

    example = ROOT / "clients" / "python" / "examples" / "plan_to_goal.py"
    common = ["--url", server, "--episodes", "2", "--max-steps", "2", "--out-steps", "2", "--candidates", "2", "--horizon", "1", "--iterations", "1"]
    for policy in ("model", "random"):
        out = subprocess.run([sys.executable, str(example), *common, "--policy", policy, "--label", policy, "--out", str(tmp_path / f"{policy}.json")],
                             capture_output=True, text=True, timeout=600)
        assert out.returncode == 0, out.stderr[-3000:]
        run = json.loads((tmp_path / f"{policy}.json").read_text())
        assert [e["goal_seen"] for e in run["episodes"]] == [True, False]
        for e in run["episodes"]:
            assert e["steps"] <= 2 and e["final_distance"] >= 0 and isinstance(e["success"], bool), e
    out = subprocess.run([sys.executable, str(example), "--compare", str(tmp_path / "model.json"), str(tmp_path / "random.json")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "paired over 2 episodes" in out.stdout, out.stdout + out.stderr
