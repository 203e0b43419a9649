"""Writes Doom walks as a `worldpack-suite/1` folder of
`worldpack-trajectory/1` trajectories (docs/dataset.md), square frames with
square pixels (64x64 unless told): the 320x240 render's centre 200 columns
(the render's pixels are 1.2 times as tall as wide), resized."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm
from worldpack_train.io.suite import walk_actions, write_trajectory

from . import engine as E
from .walk import TASKS, TURN_STEP, WALK_STEP, Geometry, Plan, start_points

SUITE_FORMAT = "worldpack-suite/1"
TRAJECTORY_FORMAT = "worldpack-trajectory/1"
SIZE = 64
CROP = (E.RENDER_WIDTH - 200) // 2, (E.RENDER_WIDTH + 200) // 2
NEAR_M, FAR_M = 0.1, 28.0   # the depth buffer saturates at about 28.8 m

# Held-out maps are never used for training data (docs/doom.md).
TEST_MAPS = ["MAP20", "MAP29", "MAP18"]
TRAIN_MAPS = [f"MAP{i:02d}" for i in range(1, 33) if f"MAP{i:02d}" not in TEST_MAPS]


def intrinsics(size: int = SIZE) -> dict:
    """The size x size camera: the render's (fx 160, fy 192, centred) cropped and resized."""
    sx, sy = size / (CROP[1] - CROP[0]), size / E.RENDER_HEIGHT
    cx0, cy0 = (E.RENDER_WIDTH - 1) / 2 - CROP[0], (E.RENDER_HEIGHT - 1) / 2
    return {"fx": E.RENDER_FX * sx, "fy": E.RENDER_FY * sy, "cx": (cx0 + 0.5) * sx - 0.5, "cy": (cy0 + 0.5) * sy - 0.5,
            "width": size, "height": size, "near": NEAR_M, "far": FAR_M}


def to_frame(view: E.View, size: int = SIZE) -> tuple[np.ndarray, np.ndarray]:
    """(rgb uint8 (size, size, 3), depth uint16 millimetres (size, size), 0 = unknown)."""
    rgb = cv2.resize(view.rgb[:, CROP[0]:CROP[1]], (size, size), interpolation=cv2.INTER_AREA)
    z = E.depth_to_units(view.depth[:, CROP[0]:CROP[1]]) / E.UNITS_PER_METRE * 1000.0
    # Depth is sampled, not averaged: an average across an edge is a surface nobody saw.
    z = cv2.resize(np.nan_to_num(z, nan=0.0).astype(np.float32), (size, size), interpolation=cv2.INTER_NEAREST)
    return rgb, np.clip(np.round(z), 0, 65535).astype(np.uint16)


def render(engine: E.Engine, plan: Plan, size: int = SIZE) -> dict:
    rgb, depth, poses = [], [], []
    for p, a in zip(plan.points, plan.angles):
        view = engine.view_at(p[0], p[1], a)
        if abs(view.x - p[0]) > 1 or abs(view.y - p[1]) > 1:
            raise RuntimeError(f"{engine.map_name}: teleport to {p} landed at ({view.x}, {view.y})")
        f, d = to_frame(view, size)
        rgb.append(f)
        depth.append(d)
        poses.append(E.map_to_world(view.c2m()))
    return {"rgb": np.stack(rgb), "depth": np.stack(depth), "poses": np.stack(poses),
            "actions": walk_actions(plan.forward, plan.yaw),
            "phase": np.array(plan.phase, np.uint8)}


def write_map(out: Path, split: str, map_name: str, count: int, ranges_m: list[float], seed: int,
              wad: str | None = None, progress=None, task: str = "aba", size: int = SIZE) -> list[dict]:
    """`count` walks of `task` (walk.TASKS) on one map; the map's own random
    stream (seed, map) makes them the same whatever else is written beside them."""
    rng = np.random.default_rng([seed, int(map_name[3:]) if map_name[3:].isdigit() else hash(map_name) % 2**31])
    engine = E.Engine(map_name, wad=wad, seed=seed)
    entries = []
    try:
        geom = Geometry(engine.sectors())
        for start, angle in start_points(engine.sectors(), geom, count * 4, rng):
            if len(entries) == count:
                break
            range_m = float(rng.choice(ranges_m))
            plan = TASKS[task](geom, start, angle, range_m * E.UNITS_PER_METRE, rng)
            if plan is None:
                continue
            arrays = render(engine, plan, size)
            name = f"{map_name.lower()}-{'' if task == 'aba' else task + '-'}r{int(range_m):02d}-{len(entries):03d}"
            frames = len(plan.points)
            meta = {"format": TRAJECTORY_FORMAT, "name": name, "split": split, "task": task, "range": int(range_m),
                    "frames": frames, "returning_point": plan.returning_point,
                    "intrinsics": intrinsics(size),
                    "world": {"kind": "doom", "wad": Path(wad or E.wad_path()).name, "map": map_name,
                              "start_map_units": [float(start[0]), float(start[1])], "seed": seed},
                    "units": {"position": "metres (32 map units)", "depth": "millimetres along the optical axis, 0 = unknown",
                              "world_axes": "x east, y up, z south (Doom map x, z, -y)"},
                    "motion": {"walk_step_m": WALK_STEP / E.UNITS_PER_METRE, "turn_step_deg": TURN_STEP}}
            write_trajectory(out, name, arrays, meta)
            entries.append({"dir": name, "task": task, "range": int(range_m), "frames": frames,
                            "returning_point": plan.returning_point, "map": map_name})
            if progress is not None:
                progress.put(1)
    finally:
        engine.close()
    return entries


def _write_map(job):
    return write_map(*job)


def write_suite(out: Path, split: str, maps: list[str], count: int, ranges_m: list[float], seed: int,
                wad: str | None = None, workers: int = 1, task: str = "aba", size: int = SIZE) -> None:
    """`count` walks of `task` spread evenly over `maps`, ranges drawn from
    `ranges_m`, maps rendered `workers` at a time."""
    import multiprocessing as mp

    out.mkdir(parents=True, exist_ok=True)
    per_map = {m: (count + len(maps) - 1 - i) // len(maps) for i, m in enumerate(maps)}
    bar = tqdm(total=count, desc=f"doom {split}", unit="walk")
    with mp.Manager() as manager:
        progress = manager.Queue()
        jobs = [(out, split, m, n, ranges_m, seed, wad, progress, task, size) for m, n in per_map.items() if n > 0]
        with mp.Pool(max(1, workers)) as pool:
            pending = pool.map_async(_write_map, jobs)
            while not pending.ready():
                pending.wait(0.5)
                while not progress.empty():
                    bar.update(progress.get())
            results = pending.get()
    bar.close()
    entries = [e for r in results for e in r]
    for (m, n), r in zip(((m, n) for m, n in per_map.items() if n > 0), results):
        if len(r) < n:
            print(f"{m}: {len(r)} of {n} walks (no more starting points with room)")
    index = {"format": SUITE_FORMAT, "kind": "doom", "split": split, "task": task, "seed": seed, "frame_size": [size, size],
             "total_frames": int(sum(e["frames"] for e in entries)), "maps": maps, "trajectories": entries}
    (out / "index.json").write_text(json.dumps(index, indent=1))
