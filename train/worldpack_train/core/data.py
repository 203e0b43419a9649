"""Reading `worldpack sim` suites and `worldpack plan` files into training
batches. Everything here is NumPy; the trainers turn batches into tensors."""

from __future__ import annotations

from dataclasses import dataclass
import json
from pathlib import Path

import numpy as np

from .config import Layout


def trajectories(root: Path) -> list[Path]:
    index = root / "index.json"
    if not index.exists():
        raise SystemExit(f"--data: no suite at {index} (make one with `worldpack sim dataset --out {root}`)")
    return [root / t["dir"] for t in json.loads(index.read_text())["trajectories"]]


def describe(root: Path) -> dict:
    """Where a model's training frames came from, for its manifest: the suite's
    folder name and what its index says of itself (docs/dataset.md)."""
    index = json.loads((root / "index.json").read_text())
    return {"suite": root.name, "kind": index.get("kind"), "split": index.get("split"), "maps": index.get("maps"),
            "trajectories": len(index["trajectories"])}


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
    # (trajectory, frame) of each target, so a trainer can gather related batches.
    rows: list[tuple[int, int]]
    # The stored frames each target's warp is made from (empty: none), with `warp`.
    warp_sources: list[list[int]] | None = None


# A target needs memory when at least this share of its view is shown only by
# frames older than the 4 newest: the threshold of the probe's memory-dependent
# stratum (eval::strata), so training and evaluation mean the same thing.
MEMORY_NEED_THRESHOLD = 0.1


class PlannedLatents:
    """Encoded latents of a suite plus one policy's plans (`plan-<policy>.npy`).

    With `memory_focus` f > 0, a share f of every batch is drawn from the
    targets that need memory (`memory-need.npy` from `worldpack plan
    --memory-need`), the rest uniformly as without it."""

    def __init__(self, root: Path, latent_dir: Path, policy: str, layout: Layout, memory_focus: float = 0.0,
                 warp: bool = False):
        if not 0.0 <= memory_focus <= 1.0:
            raise SystemExit(f"--memory-focus: must be in [0, 1], got {memory_focus}")
        self.layout = layout
        self.memory_focus = memory_focus
        plans = json.loads((root / "plans.json").read_text()) if (root / "plans.json").exists() else None
        if plans is None:
            raise SystemExit(f"--data: no plans.json in {root}; run `worldpack plan --data {root}` first")
        entry = next((p for p in plans["policies"] if p["name"] == policy), None)
        if entry is None:
            raise SystemExit(f"--policy: {root}/plans.json has no plans for {policy!r}")
        rates = entry["rates"]
        # Which view the plans scored against (plans written before this was recorded used the target pose).
        self.plans_query = entry.get("policy", {}).get("query", "target")
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
        self.warp = warp
        if warp:  # the pixels and depth warps are made from, memory-mapped
            dirs = trajectories(root)
            self.rgb = [np.load(d / "rgb.npy", mmap_mode="r") for d in dirs]
            self.depth = [np.load(d / "depth.npy", mmap_mode="r") for d in dirs]
            self.intrinsics = json.loads((dirs[0] / "meta.json").read_text())["intrinsics"]
        self.needy = np.zeros((0, 2), np.int64)
        if memory_focus > 0:
            self.needy = self.memory_targets(root)

    def memory_targets(self, root: Path) -> np.ndarray:
        """(N, 2) rows (trajectory, frame) of every target that needs memory."""
        rows = []
        for i, d in enumerate(trajectories(root)):
            path = d / "memory-need.npy"
            if not path.exists():
                raise SystemExit(f"--memory-focus: no {path}; run `worldpack plan --data {root} --memory-need` first")
            need = np.load(path)
            if need.shape != (len(self.plans[i]),):
                raise SystemExit(f"--memory-focus: {path} has shape {need.shape}, the trajectory has {len(self.plans[i])} frames")
            t = np.flatnonzero(need >= MEMORY_NEED_THRESHOLD)
            rows.append(np.stack([np.full_like(t, i), t], axis=1))
        needy = np.concatenate(rows)
        if len(needy) == 0:
            raise SystemExit(f"--memory-focus: no frame of {root} needs memory (none reaches {MEMORY_NEED_THRESHOLD})")
        return needy

    def batch(self, rng: np.random.Generator, n: int) -> Batch:
        focused = int(round(self.memory_focus * n))
        traj = rng.choice(len(self.plans), size=n - focused, p=self.sizes / self.sizes.sum())
        rows = []
        for i in traj:
            t = int(rng.integers(1, len(self.plans[i])))
            rows.append((i, t))
        if focused:
            rows += [(int(i), int(t)) for i, t in self.needy[rng.integers(len(self.needy), size=focused)]]
        return self.gather(rows, self.draw_warp_sources(rng, rows) if self.warp else None)

    # How a training target's warp sources are drawn from its plan: none (no
    # depth at hand), else 1 to WARP_FRAMES frames (the runtime fuses its
    # manifest's `warp.frames` best-overlap frames), the first of them the
    # plan's first slot (the newest or best frame) with probability
    # WARP_FIRST, the rest any selected frames (older memories warp with more
    # holes, as on a return leg).
    WARP_NONE, WARP_FIRST, WARP_FRAMES = 0.1, 0.3, 3

    def draw_warp_sources(self, rng: np.random.Generator, rows: list[tuple[int, int]]) -> list[list[int]]:
        out = []
        for i, t in rows:
            ids = self.plans[i][t]
            present = ids[ids >= 0]
            if len(present) == 0 or rng.random() < self.WARP_NONE:
                out.append([])
                continue
            n = min(len(present), int(rng.integers(1, self.WARP_FRAMES + 1)))
            if rng.random() < self.WARP_FIRST:
                rest = rng.choice(present[1:], size=n - 1, replace=False) if n > 1 else []
                out.append([int(present[0])] + [int(f) for f in rest])
            else:
                out.append([int(f) for f in rng.choice(present, size=n, replace=False)])
        return out

    def warp_pixels(self, batch: Batch):
        """NumPy inputs of `warp.forward_warp` for a batch, padded to the most
        frames any row has: source RGB (B, K, H, W, 3) and depth, source poses
        (B, K, 4, 4), target poses (B, 4, 4), and which frames are present (B, K)."""
        k = max(1, max(len(s) for s in batch.warp_sources))
        frames = [[*s, *[t] * (k - len(s))] for (_, t), s in zip(batch.rows, batch.warp_sources)]  # padding: never warped
        rgb = np.stack([[self.rgb[i][f] for f in fs] for (i, _), fs in zip(batch.rows, frames)])
        depth = np.stack([[self.depth[i][f] for f in fs] for (i, _), fs in zip(batch.rows, frames)]).astype(np.int32)
        src_pose = np.stack([[self.poses[i][f] for f in fs] for (i, _), fs in zip(batch.rows, frames)])
        dst_pose = np.stack([self.poses[i][t] for i, t in batch.rows])
        present = np.array([[n < len(s) for n in range(k)] for s in batch.warp_sources])
        return rgb, depth, src_pose, dst_pose, present

    def gather(self, rows: list[tuple[int, int]], warp_sources: list[list[int]] | None = None) -> Batch:
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
        if self.warp and warp_sources is None:  # deterministic: the first selected frame
            warp_sources = [[int(f) for f in self.plans[i][t][self.plans[i][t] >= 0][:1]] for i, t in rows]
        return Batch(np.stack(targets), np.stack(actions).astype(np.float32), np.array(rel_times, np.float32), groups,
                     list(rows), warp_sources)
