"""Training batches drawn with `--memory-focus`: a fixed share of every batch
comes from the targets that `worldpack plan --memory-need` marks as needing
memory beyond the 4 newest frames, and bad settings are refused by name.
NumPy only (the training data code needs no torch)."""

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
BIN = os.environ.get("WORLDPACK_BIN", str(ROOT / "target" / "release" / "worldpack"))
from worldpack_train.core import data as wdata
from worldpack_train.core.config import LAYOUTS

POLICY = "worldpack_keep_last"


def run(*args):
    done = subprocess.run([BIN, *args], capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    """Two ABA trajectories with keep-last plans, memory need and random latents."""
    root = tmp_path_factory.mktemp("focus")
    data, latents = root / "data", root / "latents"
    run("sim", "loopnav", "--per-cell", "2", "--tasks", "aba", "--ranges", "5", "--seed", "3", "--out", str(data))
    run("plan", "--data", str(data), "--policies", "worldpack_keep_last", "--memory-need")
    latents.mkdir()
    rng = np.random.default_rng(0)
    for d in wdata.trajectories(data):
        n = len(np.load(d / "poses.npy"))
        np.save(latents / f"{d.name}.npy", rng.standard_normal((n, 4, 16, 16)).astype(np.float16))
    return data, latents


def drawn_rows(source, seed, batches, n):
    """The (trajectory, frame) rows of `batches` batches, and the last batch."""
    rows, gather = [], source.gather

    def keep(r, *rest):
        rows.append(list(r))
        return gather(r, *rest)

    source.gather = keep
    rng = np.random.default_rng(seed)
    last = [source.batch(rng, n) for _ in range(batches)][-1]
    return rows, last


def needs(data):
    return [np.load(d / "memory-need.npy") for d in wdata.trajectories(data)]


def test_a_focused_batch_draws_its_share_from_targets_that_need_memory(suite):
    data, latents = suite
    need = needs(data)
    natural = float(np.mean(np.concatenate([n[1:] for n in need]) >= wdata.MEMORY_NEED_THRESHOLD))
    assert 0.02 < natural < 0.6, f"the suite should have some, not only, frames that need memory: {natural}"

    focused = wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY], memory_focus=0.5)
    rows, batch = drawn_rows(focused, 7, 200, 16)
    for r in rows:
        tail = r[8:]  # the focused half of each batch
        assert all(need[i][t] >= wdata.MEMORY_NEED_THRESHOLD for i, t in tail), tail
        assert all(1 <= t < len(need[i]) for i, t in r)
    share = np.mean([need[i][t] >= wdata.MEMORY_NEED_THRESHOLD for r in rows for i, t in r])
    assert abs(share - (0.5 + 0.5 * natural)) < 0.05, (share, natural)

    # Batches keep the layout's shapes: 2 + 4 + 16 slots.
    assert batch.target.shape == (16, 4, 16, 16)
    assert [g[0].shape[1] for g in batch.groups] == [2, 4, 16]


def test_without_focus_the_draw_is_uniform(suite):
    data, latents = suite
    plain = wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY])
    rows, _ = drawn_rows(plain, 7, 200, 16)
    need = needs(data)
    natural = float(np.mean(np.concatenate([n[1:] for n in need]) >= wdata.MEMORY_NEED_THRESHOLD))
    share = np.mean([need[i][t] >= wdata.MEMORY_NEED_THRESHOLD for r in rows for i, t in r])
    assert abs(share - natural) < 0.05, (share, natural)


def test_bad_focus_settings_name_the_flag(suite):
    data, latents = suite
    for bad in (-0.1, 1.5):
        with pytest.raises(SystemExit, match="--memory-focus"):
            wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY], memory_focus=bad)
    first = wdata.trajectories(data)[0] / "memory-need.npy"
    kept = first.read_bytes()
    try:
        first.unlink()
        with pytest.raises(SystemExit, match="worldpack plan --data .* --memory-need"):
            wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY], memory_focus=0.5)
        np.save(first, np.zeros(3, np.float32))
        with pytest.raises(SystemExit, match="has shape"):
            wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY], memory_focus=0.5)
    finally:
        first.write_bytes(kept)


def test_warp_sources_come_from_each_targets_own_plan(suite):
    """With `warp`, each target's warp sources are 0 to 3 distinct frames of its own
    plan (so earlier than it), the empty share is about WARP_NONE, and the pixels
    for the warp are those frames' RGB, depth and poses, padding marked absent."""
    data, latents = suite
    source = wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY], warp=True)
    rng = np.random.default_rng(5)
    counts = []
    for _ in range(40):
        batch = source.batch(rng, 32)
        for (i, t), frames in zip(batch.rows, batch.warp_sources):
            plan = set(int(f) for f in source.plans[i][t] if f >= 0)
            assert len(frames) == len(set(frames)) <= wdata.PlannedLatents.WARP_FRAMES
            assert set(frames) <= plan and all(f < t for f in frames), (i, t, frames)
            counts.append(len(frames))
    empty = counts.count(0) / len(counts)
    assert abs(empty - wdata.PlannedLatents.WARP_NONE) < 0.04, empty
    assert {1, 2, 3} <= set(counts)
    rgb, depth, src_pose, dst_pose, present = source.warp_pixels(batch)
    k = max(len(f) for f in batch.warp_sources)
    assert rgb.shape[:2] == depth.shape[:2] == src_pose.shape[:2] == present.shape == (32, k)
    for row, ((i, t), frames) in enumerate(zip(batch.rows, batch.warp_sources)):
        assert present[row].sum() == len(frames)
        for j, f in enumerate(frames):
            np.testing.assert_array_equal(rgb[row, j], source.rgb[i][f])
            np.testing.assert_array_equal(src_pose[row, j], source.poses[i][f])
        np.testing.assert_array_equal(dst_pose[row], source.poses[i][t])
    # Without `warp` nothing is drawn, and a deterministic gather takes the first planned frame.
    assert wdata.PlannedLatents(data, latents, POLICY, LAYOUTS[POLICY]).batch(rng, 4).warp_sources is None
    (i, t), = [batch.rows[0]]
    first = source.gather([(i, t)]).warp_sources[0]
    assert first == [int(source.plans[i][t][source.plans[i][t] >= 0][0])]
