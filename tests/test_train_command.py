"""`worldpack train` end to end on a tiny dataset (a few walks, a few steps per stage,
real PyTorch in the trainer's venv .venv-train, which ./scripts/test.sh makes), then a
real `worldpack serve` of the folder it wrote answering a step; and the refusals a bad
dataset or setting gets before anything is written."""

import json
import os
import shutil
import subprocess
import urllib.request
from pathlib import Path

import pytest
from test_python_client import start

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
TINY = ["--set", "autoencoder.steps=4", "--set", "autoencoder.batch=4", "--set", "baseline.steps=4", "--set", "baseline.batch=4",
        "--set", "teacher.steps=4", "--set", "teacher.batch=4", "--set", "student.steps=2", "--set", "student.batch=2",
        "--set", "heads.steps=3", "--set", "heads.batch=4", "--set", "heldout.share=0.25", "--set", "eval.limit=1"]


def worldpack(*args, cwd=ROOT):
    return subprocess.run([BIN, *map(str, args)], capture_output=True, text=True, cwd=cwd)


def suite(path, *flags):
    out = worldpack("sim", "loopnav", "--per-cell", "1", "--ranges", "5,15", "--seed", "77", "--out", path, *flags)
    assert out.returncode == 0, out.stderr
    return path


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    assert (ROOT / ".venv-train" / "bin" / "python").exists(), "no .venv-train: ./scripts/test.sh makes it (torch for the trainer)"
    tmp = tmp_path_factory.mktemp("train")
    data, out = suite(tmp / "data"), tmp / "model"
    run = worldpack("train", "--data", data, "--out", out, "--from", "voxel", *TINY)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    return data, out, run.stdout


def test_every_stage_ran_and_the_lineage_names_them(trained):
    data, out, _ = trained
    lineage = json.loads((out / "lineage.json").read_text())
    stages = lineage["stages"]
    assert list(stages) == ["check", "split", "from", "autoencoder", "baseline", "teacher", "student", "adversarial",
                            "heads", "export", "parity", "eval", "card"]
    assert all(s["status"] == "done" for n, s in stages.items() if n != "adversarial"), stages
    assert stages["adversarial"]["status"] == "skipped"  # a CPU run goes without the GPU-only stage
    assert len(stages["split"]["heldout"]) == 1 and stages["split"]["train_trajectories"] == 3
    assert stages["check"]["data"]["digest"] and stages["from"]["digests"]["served"]
    assert max(stages["parity"]["tolerance_used"].values()) <= 1.0
    settings = json.loads((out / "train.json").read_text())
    assert settings["teacher"]["steps"] == 4
    # The shipped family by its place in the repository, not this machine's path.
    assert settings["from"]["served"] == "fixtures/variants/worldpack_geometry_fused_1step"


def test_the_card_carries_the_heldout_eval_and_how_it_is_served(trained):
    _, out, _ = trained
    manifest = json.loads((out / "manifest.json").read_text())
    assert manifest["serving"] == {"policy": "worldpack", "method": "ddim", "steps": 1, "covisible": True, "warp_frames": 32}
    rows = manifest["heldout_eval"]["rows"]
    assert {"served_covisible", "started_from_covisible", "baseline", "reproject_fused"} <= set(rows)
    assert 5 < rows["served_covisible"]["psnr"]["mean"] < 60
    card = (out / "MODEL.md").read_text()
    assert f"# {out.name}" in card and "| its own 4-frame baseline" in card and "heldout-strip.png" in card
    assert (out / "heldout-strip.png").exists() and (out / "baseline" / "manifest.json").exists()


def test_a_second_run_resumes_and_trains_nothing_again(trained):
    data, out, _ = trained
    again = worldpack("train", "--data", data, "--out", out, "--from", "voxel")
    assert again.returncode == 0, again.stderr[-2000:]
    assert again.stdout.count(": done (") == 11 and "skipped" in again.stdout


def test_a_resume_may_change_the_budget_but_not_the_device(trained):
    data, out, _ = trained
    hours = json.loads((out / "train.json").read_text())["hours"]
    longer = worldpack("train", "--data", data, "--out", out, "--from", "voxel", "--hours", hours + 1)
    assert longer.returncode == 0, longer.stderr[-2000:]
    assert "the budget changes" in longer.stdout
    assert json.loads((out / "train.json").read_text())["hours"] == hours + 1
    other = worldpack("train", "--data", data, "--out", out, "--from", "voxel", "--device", "cuda")
    assert other.returncode != 0 and "'device'" in other.stderr


def test_serve_answers_a_step_with_the_model_it_made(trained, tmp_path):
    _, out, _ = trained
    proc, url = start(tmp_path, "--model", str(out))
    try:
        health = json.load(urllib.request.urlopen(url + "/v1/health"))
        manifest = json.loads((out / "manifest.json").read_text())
        assert health["model"] == out.name and health["model_version"] == manifest["version"]
        assert len(health["model_digest"]) == 16
        req = lambda path, body: json.load(urllib.request.urlopen(urllib.request.Request(
            url + path, json.dumps(body).encode(), {"content-type": "application/json"})))
        session = req("/v1/sessions", {"synthetic": {"seed": 3}})["session"]
        step = req(f"/v1/sessions/{session}/step", {"action": {"forward": True, "yaw_deg": 6}})
        assert step["image_png"] and step["steps"] == 1 and step["selection"]["warp_frames"] is not None
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def test_without_from_every_stage_trains_from_scratch_and_the_model_serves(trained, tmp_path):
    data, _, _ = trained
    out = tmp_path / "scratch"
    run = worldpack("train", "--data", data, "--out", out, *TINY)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    lineage = json.loads((out / "lineage.json").read_text())
    assert json.loads((out / "train.json").read_text())["from"] is None
    assert lineage["stages"]["from"]["status"] == "done" and "started_from_covisible" not in \
        json.loads((out / "manifest.json").read_text())["heldout_eval"]["rows"]
    proc, url = start(tmp_path, "--model", str(out))
    try:
        body = json.dumps({"synthetic": {"seed": 3}}).encode()
        req = urllib.request.Request(url + "/v1/sessions", body, {"content-type": "application/json"})
        session = json.load(urllib.request.urlopen(req))["session"]
        req = urllib.request.Request(f"{url}/v1/sessions/{session}/step", json.dumps({"action": {"forward": True}}).encode(),
                                     {"content-type": "application/json"})
        assert json.load(urllib.request.urlopen(req))["image_png"]
    finally:
        proc.terminate()
        proc.wait(timeout=30)


def refused(tmp_path, data, *extra):
    out = tmp_path / "never"
    run = worldpack("train", "--data", data, "--out", out, "--from", "voxel", *extra)
    assert run.returncode != 0
    assert not out.exists(), "a refused run wrote its output folder"
    return run.stderr + run.stdout


def test_a_dataset_that_fails_check_is_refused_naming_the_field(tmp_path):
    data = suite(tmp_path / "data")
    meta = data / "aba-r05-000" / "meta.json"
    m = json.loads(meta.read_text())
    del m["intrinsics"]["fx"]
    meta.write_text(json.dumps(m))
    assert "`intrinsics`" in refused(tmp_path, data)


def test_frames_of_another_size_are_refused(tmp_path):
    data = suite(tmp_path / "data", "--size", "48x48")
    assert "48x48" in refused(tmp_path, data)


def test_a_dataset_without_depth_is_refused(tmp_path):
    data = suite(tmp_path / "data")
    (data / "abca-r15-000" / "depth.npy").unlink()
    assert "depth.npy" in refused(tmp_path, data)


def test_too_few_walks_for_a_heldout_split_are_refused(tmp_path):
    data = suite(tmp_path / "data")
    index = json.loads((data / "index.json").read_text())
    index["trajectories"] = index["trajectories"][:2]
    (data / "index.json").write_text(json.dumps(index))
    for t in ("abca-r05-000", "abca-r15-000"):
        shutil.rmtree(data / t)
    assert "held-out split" in refused(tmp_path, data)


def test_unknown_settings_and_sources_are_refused_by_name(tmp_path):
    data = suite(tmp_path / "data")
    assert "teacher.stepz" in refused(tmp_path, data, "--set", "teacher.stepz=3")
    assert "heldout.share" in refused(tmp_path, data, "--set", "heldout.share=2")
    run = worldpack("train", "--data", data, "--out", tmp_path / "x", "--from", "quake")
    assert run.returncode != 0 and "--from" in run.stderr and not (tmp_path / "x").exists()
