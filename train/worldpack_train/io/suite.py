"""Writing walks in the dataset format (docs/dataset.md), numpy only: what the world
tools (`doom/`, `miniworld/`) share when they write their suites."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def walk_actions(forward, yaw) -> np.ndarray:
    """actions.npy of a walk whose controls are a forward key and a yaw Δ (degrees, positive
    turns right) per frame; the other five columns stay 0, and so does row 0."""
    actions = np.zeros((len(forward), 7), np.float32)
    actions[:, 0] = forward
    actions[:, 5] = yaw
    actions[0] = 0.0
    return actions


def write_trajectory(root: Path, name: str, arrays: dict, meta: dict) -> None:
    """One trajectory folder: each array as `<key>.npy`, and meta.json."""
    d = root / name
    d.mkdir(parents=True, exist_ok=True)
    for key, value in arrays.items():
        np.save(d / f"{key}.npy", value)
    (d / "meta.json").write_text(json.dumps(meta, indent=1))
