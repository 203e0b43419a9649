"""Writes MiniWorld walks as a `worldpack-suite/1` folder of
`worldpack-trajectory/1` trajectories (docs/dataset.md), rendered at 64x64.

Every walk has a world of its own: its environment reset to a world seed,
which draws MiniWorld's layout (the maze's corridors), objects, textures and
light (MiniWorld's domain randomisation, camera pinned). The splits own
disjoint world seeds; a suite's --seed owns a block of them in its split."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from tqdm import tqdm
from worldpack_train.io.suite import walk_actions, write_trajectory

from . import engine as E
from .walk import CLEARANCE, MAX_STEER, TASKS, TURN_STEP, WALK_STEP, FloorPlan

SUITE_FORMAT = "worldpack-suite/1"
TRAJECTORY_FORMAT = "worldpack-trajectory/1"

# Environment ids and the short names the trajectory folders carry.
ENVS = {
    "MiniWorld-ThreeRooms-v0": "threerooms",
    "MiniWorld-FourRooms-v0": "fourrooms",
    "MiniWorld-Maze-v0": "maze",
    "MiniWorld-TMaze-v0": "tmaze",
    "MiniWorld-PutNext-v0": "putnext",
    "MiniWorld-YMaze-v0": "ymaze",
}
TRAIN_ENVS = ["MiniWorld-ThreeRooms-v0", "MiniWorld-FourRooms-v0", "MiniWorld-Maze-v0", "MiniWorld-TMaze-v0",
              "MiniWorld-PutNext-v0"]
# The test split: the training environments at held-out world seeds, and one never trained on.
HELD_OUT_ENVS = ["MiniWorld-YMaze-v0"]
TEST_ENVS = TRAIN_ENVS + HELD_OUT_ENVS
SPLIT_ENVS = {"train": TRAIN_ENVS, "test": TEST_ENVS}

# World seeds: train [0, 1,000,000), test [1,000,000, 2,000,000). A suite with
# --seed S draws its walks in each environment from world seeds base + S*SEED_BLOCK + j, j = 0, 1, ...
SEED_BASE = {"train": 0, "test": 1_000_000}
SEED_BLOCK = 10_000
MAX_SEED = 99
GIVE_UP = 40           # world seeds in a row without a walk end an environment's share
DEFAULT_RANGES = [3.0, 6.0, 9.0]
TASK_CHOICES = ["aba", "abca", "mixed"]


def world_seed(split: str, seed: int, attempt: int) -> int:
    if not 0 <= attempt < SEED_BLOCK:
        raise ValueError(f"attempt {attempt} outside a suite seed's block of {SEED_BLOCK} world seeds")
    return SEED_BASE[split] + seed * SEED_BLOCK + attempt


def render(engine: E.Engine, plan) -> dict:
    rgb, depth, poses = [], [], []
    for p, h in zip(plan.points, plan.headings):
        f, d = engine.view(p[0], p[1], h)
        rgb.append(f)
        depth.append(d)
        poses.append(E.camera_to_world(p[0], p[1], h))
    return {"rgb": np.stack(rgb), "depth": np.stack(depth), "poses": np.stack(poses),
            "actions": walk_actions(plan.forward, plan.yaw),
            "phase": np.array(plan.phase, np.uint8)}


def _miniworld_version() -> str:
    from importlib.metadata import version

    return version("miniworld")


def write_env(engine: E.Engine, out: Path, split: str, env_id: str, count: int, ranges_m: list[float], seed: int,
              task: str, bar=None) -> list[dict]:
    """`count` walks in `env_id`, one world seed each, tried in the suite
    seed's order; `task` "mixed" alternates ABA and ABCA."""
    entries = []
    attempt = misses = 0
    while len(entries) < count and misses < GIVE_UP and attempt < SEED_BLOCK:
        ws = world_seed(split, seed, attempt)
        attempt += 1
        walk_task = task if task != "mixed" else ("aba", "abca")[len(entries) % 2]
        rng = np.random.default_rng([ws, list(ENVS).index(env_id), TASK_CHOICES.index(walk_task)])
        range_m = float(rng.choice(ranges_m))
        env = engine.load(env_id, ws)
        plan = TASKS[walk_task](FloorPlan(env), range_m, rng)
        if plan is None:
            misses += 1
            continue
        misses = 0
        arrays = render(engine, plan)
        name = f"{ENVS[env_id]}-{walk_task}-r{int(round(range_m)):02d}-{ws:07d}"
        frames = len(plan)
        meta = {"format": TRAJECTORY_FORMAT, "name": name, "split": split, "task": walk_task, "range": int(round(range_m)),
                "frames": frames, "returning_point": plan.returning_point, "intrinsics": E.intrinsics(engine.size),
                "world": {"kind": "miniworld", "env": env_id, "world_seed": ws, "suite_seed": seed,
                          "miniworld": _miniworld_version(), "domain_rand": True,
                          "start": [float(plan.points[0][0]), float(plan.points[0][1])]},
                "units": {"position": "metres (MiniWorld's own)", "depth": "millimetres along the optical axis, 0 = unknown",
                          "world_axes": "MiniWorld's: y up; heading a faces (cos a, 0, -sin a)"},
                "camera": {"eye_height_m": E.EYE_HEIGHT, "vfov_deg": E.VFOV_DEG, "rgb_samples": E.RGB_SAMPLES},
                "motion": {"walk_step_m": WALK_STEP, "turn_step_deg": TURN_STEP, "max_steer_deg": MAX_STEER,
                           "clearance_m": CLEARANCE}}
        write_trajectory(out, name, arrays, meta)
        entries.append({"dir": name, "task": walk_task, "range": int(round(range_m)), "frames": frames,
                        "returning_point": plan.returning_point, "env": env_id, "world_seed": ws})
        if bar is not None:
            bar.update(1)
    return entries


def write_suite(out: Path, split: str, envs: list[str], count: int, ranges_m: list[float], seed: int,
                task: str = "aba", gl: str = "egl", size: int = E.SIZE) -> dict:
    """`count` walks of `task` spread evenly over `envs` (one process, one
    environment at a time); returns the index it wrote."""
    out.mkdir(parents=True, exist_ok=True)
    per_env = {e: (count + len(envs) - 1 - i) // len(envs) for i, e in enumerate(envs)}
    engine = E.Engine(gl=gl, size=size)
    entries = []
    try:
        with tqdm(total=count, desc=f"miniworld {split}", unit="walk") as bar:
            for env_id, n in per_env.items():
                if n == 0:
                    continue
                got = write_env(engine, out, split, env_id, n, ranges_m, seed, task, bar)
                if len(got) < n:
                    tqdm.write(f"{env_id}: {len(got)} of {n} walks ({GIVE_UP} world seeds in a row had no {task} walk "
                               f"at ranges {','.join(f'{r:g}' for r in ranges_m)})")
                entries += got
    finally:
        engine.close()
    index = {"format": SUITE_FORMAT, "kind": "miniworld", "split": split, "task": task, "seed": seed,
             "frame_size": [size, size], "total_frames": int(sum(e["frames"] for e in entries)), "envs": envs,
             "ranges": ranges_m, "world_seeds": [world_seed(split, seed, 0), world_seed(split, seed, SEED_BLOCK - 1)],
             "trajectories": entries}
    (out / "index.json").write_text(json.dumps(index, indent=1))
    return index
