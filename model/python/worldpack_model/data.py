"""Reading `worldpack sim` suites and `worldpack plan` files into training
batches. Everything here is NumPy; the trainers turn batches into tensors."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .config import Layout


def trajectories(root: Path) -> list[Path]:
    index = root / "index.json"
    if not index.exists():
        raise SystemExit(f"--data: no suite at {index} (make one with `worldpack sim dataset --out {root}`)")
    return [root / t["dir"] for t in json.loads(index.read_text())["trajectories"]]


def to_unit_range(rgb_u8: np.ndarray) -> np.ndarray:
    """(..., H, W, 3) uint8 -> (..., 3, H, W) float32 in [-1, 1]."""
    x = rgb_u8.astype(np.float32) / 127.5 - 1.0
    return np.moveaxis(x, -1, -3)


class Frames:
    """Random RGB frames across a suite, memory-mapped."""

    def __init__(self, root: Path):
        self.rgb = [np.load(d / "rgb.npy", mmap_mode="r") for d in trajectories(root)]
        self.sizes = np.array([len(r) for r in self.rgb])

    def __len__(self) -> int:
        return int(self.sizes.sum())

    def batch(self, rng: np.random.Generator, n: int) -> np.ndarray:
        traj = rng.choice(len(self.rgb), size=n, p=self.sizes / self.sizes.sum())
        return to_unit_range(np.stack([self.rgb[i][rng.integers(self.sizes[i])] for i in traj]))


def relative_poses(target_c2w: np.ndarray, context_c2w: np.ndarray) -> np.ndarray:
    """Each context camera in the target camera's frame (OpenCV axes):
    inv(T_target) @ T_context, top 3x4 rows flattened row-major -> (..., 12)."""
    r_t = target_c2w[..., None, :3, :3]
    p_t = target_c2w[..., None, :3, 3]
    r = np.swapaxes(r_t, -1, -2) @ context_c2w[..., :3, :3]
    p = (np.swapaxes(r_t, -1, -2) @ (context_c2w[..., :3, 3] - p_t)[..., None])[..., 0]
    return np.concatenate([r, p[..., None]], axis=-1).reshape(*r.shape[:-2], 12).astype(np.float32)


@dataclass
class Batch:
    """One training batch for a layout. `groups[i]` belongs to `layout.rates[i]`:
    (latents (B,S,C,h,w), time offsets (B,S) = frame time - target time,
    relative poses (B,S,12), mask (B,S) 1 = present)."""

    target: np.ndarray
    action: np.ndarray
    rel_time: np.ndarray
    groups: list[tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


class PlannedLatents:
    """Encoded latents of a suite plus one policy's plans (`plan-<policy>.npy`)."""

    def __init__(self, root: Path, latent_dir: Path, policy: str, layout: Layout):
        self.layout = layout
        plans = json.loads((root / "plans.json").read_text()) if (root / "plans.json").exists() else None
        if plans is None:
            raise SystemExit(f"--data: no plans.json in {root}; run `worldpack plan --data {root}` first")
        entry = next((p for p in plans["policies"] if p["name"] == policy), None)
        if entry is None:
            raise SystemExit(f"--policy: {root}/plans.json has no plans for {policy!r}")
        rates = entry["rates"]
        expected = [r for r, c in zip(layout.rates, layout.counts) for _ in range(c)]
        if rates != expected:
            raise SystemExit(f"--policy: plans for {policy!r} have slot rates {rates}, layout {layout.name} needs {expected}")
        self.latents, self.poses, self.actions, self.plans = [], [], [], []
        for d in trajectories(root):
            self.latents.append(np.load(latent_dir / f"{d.name}.npy", mmap_mode="r"))
            self.poses.append(np.load(d / "poses.npy"))
            self.actions.append(np.load(d / "actions.npy"))
            self.plans.append(np.load(d / entry["file"]))
        self.sizes = np.array([len(p) - 1 for p in self.plans])  # frame 0 has no context

    def batch(self, rng: np.random.Generator, n: int) -> Batch:
        traj = rng.choice(len(self.plans), size=n, p=self.sizes / self.sizes.sum())
        rows = []
        for i in traj:
            t = int(rng.integers(1, len(self.plans[i])))
            rows.append((i, t))
        return self.gather(rows)

    def gather(self, rows: list[tuple[int, int]]) -> Batch:
        targets, actions, rel_times, slots = [], [], [], []
        for i, t in rows:
            ids = self.plans[i][t]
            present = ids >= 0
            safe = np.where(present, ids, 0)
            lat = np.asarray(self.latents[i][safe], dtype=np.float32) * present[:, None, None, None]
            offsets = np.where(present, safe - t, 0).astype(np.float32)
            rel = relative_poses(self.poses[i][t], self.poses[i][safe])
            rel[~present] = 0.0
            targets.append(np.asarray(self.latents[i][t], dtype=np.float32))
            actions.append(self.actions[i][t])
            rel_times.append(float(t - ids[present].max()))
            slots.append((lat, offsets, rel, present.astype(np.float32)))
        groups, start = [], 0
        for count in self.layout.counts:
            part = slice(start, start + count)
            groups.append(tuple(np.stack([s[k][part] for s in slots]) for k in range(4)))
            start += count
        return Batch(np.stack(targets), np.stack(actions).astype(np.float32), np.array(rel_times, np.float32), groups)
